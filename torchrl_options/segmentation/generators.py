"""Demonstrations produced by a known sequence of skills, with ground-truth segment boundaries.

Two benchmarks for segmentation (Fox et al., 2017, section 5.3, scored the segmentation of surgical
demonstrations against expert annotations; that data is not public, so these generators plant the truth):

- :func:`reach_grasp_demonstrations`: continuous actions. A point gripper in the unit square reaches an object,
  grasps it, carries it to a drop point and releases it: four skills with noisy continuous actions.
- :func:`gridworld_subgoal_demonstrations`: discrete actions. A hierarchical supervisor in a GridWorld tours
  sub-goals, each reached by the value-iteration shortest-path policy; by default the four dead ends of
  :func:`diamond_map`, a map designed so that the skills can be told apart from the data (or the room centres of
  the paper's four-rooms map, an ambiguous variant).

Both return a ``[B, T]`` TensorDict in :class:`~torchrl_options.DDOLoss`'s layout (``observation``, ``action``,
``("next", "observation")``, ``("collector", "mask")``, ``("next", "terminated")``) plus the ground truth:
``true_option`` (long, the skill active at each step, ``-1`` on padding) and ``true_switch`` (bool, a skill
starts at the step; ``True`` at ``t = 0``), like :func:`~torchrl_options.testing.planted_corridor_demonstrations`.
"""
from __future__ import annotations

import math
from pathlib import Path

import torch
from tensordict import TensorDict

from torchrl_options.checks import check_int

__all__ = [
    "REACH_GRASP_SKILLS",
    "dead_ends",
    "default_subgoals",
    "diamond_map",
    "gridworld_subgoal_demonstrations",
    "reach_grasp_demonstrations",
    "room_centers",
]

REACH_GRASP_SKILLS = ("reach object", "grasp", "carry to drop point", "release")


def _far_point(anchor: torch.Tensor, min_distance: float, g: torch.Generator) -> torch.Tensor:
    """Uniform points of the unit square at least ``min_distance`` from ``anchor`` ``[B, 2]`` (rejection)."""
    out = torch.rand(anchor.shape, generator=g)
    bad = (out - anchor).norm(dim=-1) < min_distance
    while bad.any():
        out[bad] = torch.rand(int(bad.sum()), 2, generator=g)
        bad = (out - anchor).norm(dim=-1) < min_distance
    return out


def reach_grasp_demonstrations(
    num_trajectories: int = 32,
    *,
    max_length: int = 300,
    speed: float = 0.02,
    radius: float = 0.05,
    grip_rate: float = 0.03,
    action_noise: float = 0.3,
    min_distance: float = 0.4,
    seed: int = 0,
) -> TensorDict:
    """Pick-and-place demonstrations of a point gripper with four planted skills and noisy continuous actions.

    The state is the gripper position ``p`` in the unit square, its closure ``g`` in ``[0, 1]`` (0 open) and a
    ``holding`` flag. Each trajectory draws a start ``p_0``, an object position ``A`` and a drop point ``B``
    (uniform, ``|A - p_0| >= min_distance`` and ``|B - A| >= min_distance``) and runs the skills in order:

    0. *reach object*: move toward ``A``; ends when ``|A - p| < radius``;
    1. *grasp*: stay, close the gripper; ends when ``g = 1`` (then ``holding = 1``);
    2. *carry*: move toward ``B``; ends when ``|B - p| < radius``;
    3. *release*: stay, open the gripper; ends when ``g = 0`` (then ``holding = 0``), and so does the trajectory.

    The action ``a = (v_x, v_y, v_g)`` is a command in units of the top speed: a reaching skill commands the unit
    vector toward its target and ``v_g = 0``, grasp ``(0, 0, +1)`` and release ``(0, 0, -1)``; Gaussian noise of
    standard deviation ``action_noise`` is added to every component, and the noisy command is executed:
    ``p += speed * (v_x, v_y)``, ``g = clip(g + grip_rate * v_g, 0, 1)``. Each skill's end is a function of the
    next observation, as DDO's termination model assumes. Trajectories end with the release (padded to the
    longest; ``("next", "terminated")`` is set at the last step) or are cut at ``max_length`` steps.

    With the defaults a segment lasts about 35 steps (reaches of at least 18 steps, grasp/release about 34).

    Args:
        num_trajectories (int): B.

    Keyword Args:
        max_length (int): the longest trajectory. Defaults to 300.
        speed (float): distance per step at a unit command. Defaults to 0.02.
        radius (float): a reach ends within this distance of its target. Defaults to 0.05.
        grip_rate (float): closure change per step at a unit command. Defaults to 0.03.
        action_noise (float): standard deviation of the action noise. Defaults to 0.3.
        min_distance (float): between the start and ``A``, and between ``A`` and ``B``. Defaults to 0.4.
        seed (int): generator seed.

    Returns:
        A ``[B, T]`` TensorDict: ``"observation"`` float ``[B, T, 10]`` = ``(p, e_A, |A - p|, e_B, |B - p|, g,
        holding)`` with ``e_X`` the unit vector from ``p`` toward ``X`` (what a robot's target sensor gives),
        ``"action"`` float ``[B, T, 3]``, ``("next", "observation")``, ``("next", "terminated")`` ``[B, T, 1]``,
        ``("collector", "mask")``, ``"true_option"`` (the skill index of :data:`REACH_GRASP_SKILLS`, ``-1`` on
        padding), ``"true_switch"`` and ``"waypoints"`` ``[B, T, 2, 2]`` (``A`` and ``B``).

    Examples:
        >>> data = reach_grasp_demonstrations(4, seed=0)
        >>> data["observation"].shape[-1], data["action"].shape[-1]
        (10, 3)
        >>> [int(x) for x in data["true_option"].unique()]  # all four skills, and padding
        [-1, 0, 1, 2, 3]
        >>> bool(data["true_switch"].sum(1).eq(4).all())  # four skills per trajectory
        True
    """
    if num_trajectories < 1 or max_length < 1:
        raise ValueError(f"num_trajectories and max_length must be positive, got {num_trajectories}, {max_length}.")
    if not (speed > 0 and radius > speed / 2 and grip_rate > 0 and action_noise >= 0):
        raise ValueError(
            f"need speed > 0, radius > speed / 2, grip_rate > 0 and action_noise >= 0, got speed={speed}, "
            f"radius={radius}, grip_rate={grip_rate}, action_noise={action_noise}."
        )
    if not 0 <= min_distance < 0.9:
        raise ValueError(f"min_distance must be in [0, 0.9) (inside the unit square), got {min_distance}.")
    g = torch.Generator().manual_seed(seed)
    B = num_trajectories
    p = torch.rand(B, 2, generator=g)
    A = _far_point(p, min_distance, g)
    Bp = _far_point(A, min_distance, g)
    grip = torch.zeros(B)
    holding = torch.zeros(B)
    skill = torch.zeros(B, dtype=torch.long)
    switch = torch.ones(B, dtype=torch.bool)
    alive = torch.ones(B, dtype=torch.bool)

    def observe():
        to_a, to_b = A - p, Bp - p
        dist_a, dist_b = to_a.norm(dim=-1, keepdim=True), to_b.norm(dim=-1, keepdim=True)
        return torch.cat(
            [p, to_a / dist_a.clamp_min(1e-8), dist_a, to_b / dist_b.clamp_min(1e-8), dist_b, grip[:, None],
             holding[:, None]], -1,
        )

    obs, actions, next_obs, skills, switches, masks, ends = [], [], [], [], [], [], []
    for _ in range(max_length):
        if not alive.any():
            break
        obs.append(observe())
        target = torch.where((skill == 0)[:, None], A, Bp)
        delta = target - p
        direction = delta / delta.norm(dim=-1, keepdim=True).clamp_min(1e-8)
        moving = (skill == 0) | (skill == 2)
        v = torch.where(moving[:, None], direction, 0.0)
        vg = torch.where(skill == 1, 1.0, torch.where(skill == 3, -1.0, 0.0))
        action = torch.cat([v, vg[:, None]], -1) + action_noise * torch.randn(B, 3, generator=g)
        action = torch.where(alive[:, None], action, 0.0)
        actions.append(action)
        skills.append(torch.where(alive, skill, -1))
        switches.append(switch & alive)
        masks.append(alive.clone())
        p = torch.where(alive[:, None], p + speed * action[:, :2], p)
        grip = torch.where(alive, (grip + grip_rate * action[:, 2]).clamp(0.0, 1.0), grip)
        reached_a = (skill == 0) & ((A - p).norm(dim=-1) < radius)
        closed = (skill == 1) & (grip >= 1.0)
        reached_b = (skill == 2) & ((Bp - p).norm(dim=-1) < radius)
        opened = (skill == 3) & (grip <= 0.0)
        holding = torch.where(closed, 1.0, torch.where(opened, 0.0, holding))
        next_obs.append(observe())
        done = (reached_a | closed | reached_b | opened) & alive
        finished = opened & alive
        ends.append(finished)
        skill = torch.where(done & ~finished, skill + 1, skill)
        switch = done & ~finished
        alive = alive & ~finished
    T = len(obs)
    mask = torch.stack(masks, 1)
    zero = torch.zeros((), dtype=torch.float32)
    observation = torch.where(mask[..., None], torch.stack(obs, 1), zero)
    waypoints = torch.stack([A, Bp], 1)[:, None].expand(B, T, 2, 2)
    return TensorDict(
        {
            "observation": observation,
            "action": torch.stack(actions, 1),
            "next": {
                "observation": torch.where(mask[..., None], torch.stack(next_obs, 1), zero),
                "terminated": torch.stack(ends, 1)[..., None],
            },
            ("collector", "mask"): mask,
            "true_option": torch.stack(skills, 1),
            "true_switch": torch.stack(switches, 1),
            "waypoints": waypoints.clone(),
        },
        batch_size=[B, T],
    )


def _around(cells: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """Cells listed around the map (clockwise, by angle about their mean), so that consecutive ones are neighbours
    on a round."""
    if len(cells) <= 2:
        return list(cells)
    mean = torch.tensor(cells, dtype=torch.float64).mean(0)
    angle = [math.atan2(c - mean[1].item(), -(r - mean[0].item())) for r, c in cells]
    return [cells[i] for i in sorted(range(len(cells)), key=lambda i: angle[i])]


def room_centers(grid) -> list[tuple[int, int]]:
    """The centre of each room of a GridWorld map (the room cell closest to the room's centroid), listed around
    the map (by angle about the mean of the centres), so that consecutive rooms are neighbours on a round.

    Examples:
        >>> room_centers("four-rooms")
        [(12, 2), (2, 2), (2, 8), (12, 8)]
    """
    from torchrl_options.envs.maps import load_map

    grid = load_map(grid)
    centers = []
    for cells in grid.room_cells:
        pos = grid.free_cells[cells].float()
        centroid = pos.mean(0)
        best = (pos - centroid).norm(dim=-1).argmin()
        centers.append(tuple(int(v) for v in grid.free_cells[cells[best]]))
    return _around(centers)


def dead_ends(grid) -> list[tuple[int, int]]:
    """The dead ends of a GridWorld map (free cells with exactly one free neighbour), listed around the map like
    :func:`room_centers`.

    Examples:
        >>> dead_ends(diamond_map(2, 1))
        [(4, 1), (1, 4), (4, 7), (7, 4)]
        >>> dead_ends("four-rooms")
        []
    """
    from torchrl_options.envs.maps import load_map

    grid = load_map(_resolve_grid(grid))
    moved = grid.next_cell != torch.arange(grid.num_free)[:, None]
    ends = grid.free_cells[moved.sum(1) == 1]
    return _around([tuple(int(v) for v in pos) for pos in ends])


def diamond_map(radius: int = 4, spur: int = 3):
    """A GridWorld map for segmentation: a diamond-shaped ring of four staircase corridors, with a dead-end spur
    at each vertex.

    The ring's vertices are at the top, right, bottom and left of the diamond, ``2 * radius`` moves apart; each
    side is a one-cell-wide staircase that alternates a horizontal and a vertical move (so walking a side takes
    ``radius`` moves of each of two kinds, in turn). A straight spur of ``spur`` cells leaves each vertex outward
    and ends in a dead end. Every free cell is a corridor cell (no rooms, no 2x2 free block), so walls block every
    move but the two along the corridor (three at a vertex). The map is ``2 * radius + 2 * spur + 3`` cells square.

    It is the default map of :func:`gridworld_subgoal_demonstrations`, whose sub-goals are then the four dead ends
    (see there why).

    Args:
        radius (int): moves of each kind along a side (at least 2). Defaults to 4.
        spur (int): cells per spur (at least 1). Defaults to 3.

    Returns:
        GridMap: named ``"diamond-{radius}-{spur}"``, without start or goal markers.

    Examples:
        >>> grid = diamond_map(2, 1)
        >>> for row in grid.walls.int().tolist():
        ...     print("".join(".#"[v] for v in row))
        #########
        ####.####
        ###...###
        ##..#..##
        #...#...#
        ##..#..##
        ###...###
        ####.####
        #########
        >>> diamond_map().num_free, diamond_map().num_rooms, dead_ends(diamond_map())
        (44, 0, [(8, 1), (1, 8), (8, 15), (15, 8)])
    """
    from torchrl_options.envs.maps import GridMap

    if radius < 2 or spur < 1:
        raise ValueError(f"radius must be at least 2 and spur at least 1; got radius={radius}, spur={spur}.")
    R = radius
    n = 2 * R + 2 * spur + 3
    o = spur + 1  # the diamond's bounding box starts at (o, o); vertices (0, R), (R, 2R), (2R, R), (R, 0)
    walls = torch.ones(n, n, dtype=torch.bool)
    cells = []
    for k in range(R):
        cells += [(k, R + k), (k, R + k + 1)]  # top -> right: right, then down
        cells += [(R + k, 2 * R - k), (R + k + 1, 2 * R - k)]  # right -> bottom: down, then left
        cells += [(2 * R - k, R - k), (2 * R - k, R - k - 1)]  # bottom -> left: left, then up
        cells += [(R - k, k), (R - k - 1, k)]  # left -> top: up, then right
    for j in range(1, spur + 1):
        cells += [(-j, R), (R, 2 * R + j), (2 * R + j, R), (R, -j)]
    for r, c in cells:
        walls[o + r, o + c] = False
    return GridMap(walls=walls, name=f"diamond-{radius}-{spur}")


def default_subgoals(grid) -> list[tuple[int, int]]:
    """The default sub-goals of :func:`gridworld_subgoal_demonstrations` on a map: its dead ends when it has at
    least two (:func:`dead_ends`), its rooms' centres otherwise (:func:`room_centers`).

    Examples:
        >>> default_subgoals("diamond")
        [(8, 1), (1, 8), (8, 15), (15, 8)]
        >>> default_subgoals("four-rooms")
        [(12, 2), (2, 2), (2, 8), (12, 8)]
    """
    from torchrl_options.envs.maps import load_map

    grid = load_map(_resolve_grid(grid))
    ends = dead_ends(grid)
    return ends if len(ends) >= 2 else room_centers(grid)


def _resolve_grid(grid):
    """``"diamond"`` is :func:`diamond_map` with its defaults; anything else is left to ``load_map``."""
    return diamond_map() if isinstance(grid, str) and grid == "diamond" else grid


def gridworld_subgoal_demonstrations(
    num_trajectories: int = 32,
    length: int = 200,
    *,
    grid: str | Path = "diamond",
    subgoals: str | list[tuple[int, int]] | None = None,
    noise: float = 0.3,
    tour: str = "patrol",
    one_hot: bool = True,
    seed: int = 0,
) -> TensorDict:
    """Demonstrations of a hierarchical GridWorld supervisor that tours sub-goals, with the true switch points.

    Skill ``k`` is "go to sub-goal ``k``", acted by the optimal policy of
    :func:`~torchrl_options.envs.value_iteration` toward that cell (ties broken at random). The agent starts in a
    uniformly random free cell with a random sub-goal other than its own cell; when it reaches the active
    sub-goal, a new segment starts at the next step with the next sub-goal: with ``tour="patrol"`` (default) the
    following one in the order of ``subgoals`` (listed around the map, so a patrol goes round), with
    ``tour="random"`` one drawn uniformly among the others. The dynamics are
    :class:`~torchrl_options.envs.GridWorldEnv`'s: the chosen move is replaced by a uniformly random one with
    probability ``noise`` and walls block moves. The recorded action is the one the supervisor chose (as in
    :func:`~torchrl_options.envs.generate_demonstrations`). The observation is the agent's cell only (one-hot
    over the free cells, or its normalised ``(row, col)``): the active sub-goal is not observed, and must be
    inferred, as in a real demonstration.

    **Default design** (``grid="diamond"``, :func:`diamond_map`; sub-goals its four dead ends; patrol). A
    segmentation benchmark needs skills that can be told apart from (state, action) data; this one is built so:

    - every sub-goal is a dead end, so the agent turns back there: the moves just before and just after a true
      boundary are opposite moves in the same cells, which one option can only explain both of at a cost, so the
      data pin the boundary to within a step;
    - on a patrol each corridor cell is crossed in each direction by one skill only, so nothing in the data calls
      for a cut between dead ends;
    - the corridors are staircases, so a skill alternates two moves at every step: skills are not runs of one
      action, and cutting where the action changes (a detector that needs no model) scores about 0.08.

    With the defaults a segment lasts about 19 steps (14 moves, slowed by the noise). DDO with 8 options (twice
    the sub-goals) recovers the boundaries with accuracy about 0.95 at +-1 step, random boundaries about 0.14
    (``benchmarks/bench_segmentation.py``). The first segment of a trajectory starts in a random cell toward a
    random sub-goal, so it may run a corridor the other way round than the patrol; most of DDO's few wrong
    boundaries are there.

    **Four-rooms variant** (``grid="four-rooms"``: sub-goals the room centres, :func:`room_centers`). The
    supervisor patrols the corner rooms through the one-cell corridors of the H. DDO finds nearly every true
    boundary but also cuts the skills in the corridors (boundary accuracy about 0.64 at +-1 step with 4 or 8
    options), at a likelihood clearly below that of options started from the true skills (seen with 4 options:
    -0.167 against -0.126 nats per step): local optima, in a landscape where skills move in one direction over
    long stretches (cutting where the action changes scores about 0.41 there). ``tour="random"`` is harder
    still: skills share long path prefixes (every way out of a dead end is the same corridor).

    Args:
        num_trajectories (int): B.
        length (int): T, steps per trajectory (all valid).

    Keyword Args:
        grid: ``"diamond"`` (default, :func:`diamond_map` with its defaults), a built-in map name
            (:func:`~torchrl_options.envs.available_maps`), a map file or a :class:`~torchrl_options.envs.GridMap`
            (e.g. ``diamond_map(radius=6, spur=4)`` for longer segments).
        subgoals: ``None`` (default: :func:`default_subgoals`, the map's dead ends when it has two or more, else
            its rooms' centres), ``"dead-ends"``, ``"room-centers"``, or a list of ``(row, col)`` cells, in tour
            order.
        noise (float): the env's action noise. Defaults to 0.3 (the paper's).
        tour (str): ``"patrol"`` (default) or ``"random"``, the choice of the next sub-goal.
        one_hot (bool): one-hot observation (default) or normalised coordinates.
        seed (int): generator seed.

    Returns:
        A ``[B, T]`` TensorDict: ``"observation"`` (float ``[B, T, F]`` one-hot, or ``[B, T, 2]``), ``"action"``
        (long), ``"agent_pos"`` (long ``[B, T, 2]``), ``("next", "observation")``, ``("next", "agent_pos")``,
        ``("next", "terminated")`` (all False), ``("collector", "mask")`` (all True), ``"true_option"`` (the
        sub-goal index) and ``"true_switch"``.

    Examples:
        >>> data = gridworld_subgoal_demonstrations(4, 100, seed=0)
        >>> data["observation"].shape, data["action"].dtype  # one-hot over the 44 cells of the diamond
        (torch.Size([4, 100, 44]), torch.int64)
        >>> bool((data["true_switch"].sum(1) > 2).all())  # several sub-goals reached per trajectory
        True
        >>> gridworld_subgoal_demonstrations(2, 50, grid="four-rooms")["observation"].shape[-1]
        53
    """
    from torchrl_options.envs.maps import load_map
    from torchrl_options.envs.supervisor import value_iteration

    check_int(num_trajectories, "num_trajectories", minimum=1)
    check_int(length, "length", minimum=1)
    grid = load_map(_resolve_grid(grid))
    subgoals = default_subgoals(grid) if subgoals is None else subgoals
    if isinstance(subgoals, str):
        if subgoals not in ("dead-ends", "room-centers"):
            raise ValueError(f"subgoals must be 'dead-ends', 'room-centers' or a list of cells, got {subgoals!r}.")
        subgoals = dead_ends(grid) if subgoals == "dead-ends" else room_centers(grid)
    subgoals = [tuple(int(v) for v in s) for s in subgoals]
    if len(subgoals) < 2:
        raise ValueError(f"subgoals needs at least two cells, got {subgoals}.")
    for s in subgoals:
        if grid.is_wall(s):
            raise ValueError(f"subgoal {s} is a wall or outside map {grid.name!r}.")
    if not 0.0 <= noise < 1.0:
        raise ValueError(f"noise must be in [0, 1), got {noise}.")
    if tour not in ("patrol", "random"):
        raise ValueError(f"tour must be 'patrol' or 'random', got {tour!r}.")
    B, T, F, K = num_trajectories, length, grid.num_free, len(subgoals)
    g = torch.Generator().manual_seed(seed)
    _, q = value_iteration(grid, noise)
    goal_cells = torch.tensor([int(grid.cell_index[r, c]) for r, c in subgoals])
    q = q[goal_cells].float()  # [K, F, 4]
    best = q.min(-1, keepdim=True).values
    optimal = q <= best + 1e-5 * (1.0 + best.abs())
    nxt = grid.next_cell
    H, W = grid.shape
    scale = torch.tensor([max(H - 1, 1), max(W - 1, 1)], dtype=torch.float32)

    def observe(cells):
        if one_hot:
            return torch.nn.functional.one_hot(cells, F).float()
        return grid.free_cells[cells].float() / scale

    def draw_other(excluded):  # a uniform sub-goal index other than `excluded` ([B] long, -1 for none)
        k = torch.randint(K - 1, (B,), generator=g)
        k = torch.where(excluded >= 0, k + (k >= excluded).long(), torch.randint(K, (B,), generator=g))
        return k

    cell = torch.randint(F, (B,), generator=g)
    at_goal = (cell[:, None] == goal_cells[None]).long()
    option = draw_other(torch.where(at_goal.any(1), at_goal.argmax(1), -1))
    switch = torch.ones(B, dtype=torch.bool)
    obs, actions, next_obs, pos, next_pos, options, switches = [], [], [], [], [], [], []
    for _ in range(T):
        obs.append(observe(cell))
        pos.append(grid.free_cells[cell])
        options.append(option.clone())
        switches.append(switch.clone())
        scores = torch.rand(B, 4, generator=g) + optimal[option, cell].float()
        action = scores.argmax(-1)
        actions.append(action)
        replace = torch.rand(B, generator=g) < noise
        executed = torch.where(replace, torch.randint(4, (B,), generator=g), action)
        cell = nxt[cell, executed]
        next_obs.append(observe(cell))
        next_pos.append(grid.free_cells[cell])
        reached = cell == goal_cells[option]
        following = (option + 1) % K if tour == "patrol" else draw_other(option)
        option = torch.where(reached, following, option)
        switch = reached
    return TensorDict(
        {
            "observation": torch.stack(obs, 1),
            "action": torch.stack(actions, 1),
            "agent_pos": torch.stack(pos, 1),
            "next": {
                "observation": torch.stack(next_obs, 1),
                "agent_pos": torch.stack(next_pos, 1),
                "terminated": torch.zeros(B, T, 1, dtype=torch.bool),
            },
            ("collector", "mask"): torch.ones(B, T, dtype=torch.bool),
            "true_option": torch.stack(options, 1),
            "true_switch": torch.stack(switches, 1),
        },
        batch_size=[B, T],
    )
