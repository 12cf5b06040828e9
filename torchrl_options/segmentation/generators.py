"""Demonstrations produced by a known sequence of skills, with ground-truth segment boundaries.

Two benchmarks for segmentation (Fox et al., 2017, section 5.3, scored the segmentation of surgical
demonstrations against expert annotations; that data is not public, so these generators plant the truth):

- :func:`reach_grasp_demonstrations`: continuous actions. A point gripper in the unit square reaches an object,
  grasps it, carries it to a drop point and releases it: four skills with noisy continuous actions.
- :func:`gridworld_subgoal_demonstrations`: discrete actions. A hierarchical supervisor in a GridWorld tours
  sub-goals (the rooms' centres), each reached by the value-iteration shortest-path policy.

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

__all__ = ["REACH_GRASP_SKILLS", "reach_grasp_demonstrations", "gridworld_subgoal_demonstrations", "room_centers"]

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
    if len(centers) > 2:
        mean = torch.tensor(centers, dtype=torch.float64).mean(0)
        angle = [math.atan2(c - mean[1].item(), -(r - mean[0].item())) for r, c in centers]
        centers = [centers[i] for i in sorted(range(len(centers)), key=lambda i: angle[i])]
    return centers


def gridworld_subgoal_demonstrations(
    num_trajectories: int = 32,
    length: int = 200,
    *,
    grid: str | Path = "four-rooms",
    subgoals: list[tuple[int, int]] | None = None,
    noise: float = 0.3,
    tour: str = "patrol",
    one_hot: bool = True,
    seed: int = 0,
) -> TensorDict:
    """Demonstrations of a hierarchical GridWorld supervisor that tours sub-goals, with the true switch points.

    Skill ``k`` is "go to sub-goal ``k``" (by default the rooms' centres, :func:`room_centers`), acted by the
    optimal policy of :func:`~torchrl_options.envs.value_iteration` toward that cell (ties broken at random). The
    agent starts in a uniformly random free cell with a random sub-goal other than its own cell; when it reaches
    the active sub-goal, a new segment starts at the next step with the next sub-goal: with ``tour="patrol"``
    (default) the following one in the order of ``subgoals`` (a round of the rooms, which :func:`room_centers`
    lists around the map), with ``tour="random"`` one drawn uniformly among the others.

    With random tours, skills share long path prefixes (every way out of a four-rooms corner room is the same
    corridor), so which skill is running is unidentifiable from the actions until the paths part: a harder,
    ambiguous benchmark, where DDO tends to cut segments where the paths part. A patrol visits the rooms in turn,
    so each stretch of corridor is crossed in one direction by one skill. The dynamics are :class:`~torchrl_options.envs.GridWorldEnv`'s: the chosen move is replaced by a
    uniformly random one with probability ``noise`` and walls block moves. The recorded action is the one the
    supervisor chose (as in :func:`~torchrl_options.envs.generate_demonstrations`).

    The observation is the agent's cell only (one-hot over the free cells, or its normalised ``(row, col)``): the
    active sub-goal is not observed, and must be inferred, as in a real demonstration.

    Args:
        num_trajectories (int): B.
        length (int): T, steps per trajectory (all valid).

    Keyword Args:
        grid: a built-in map name, a map file or a :class:`~torchrl_options.envs.GridMap`.
        subgoals (list of (row, col), optional): defaults to the rooms' centres.
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
        >>> data["observation"].shape, data["action"].dtype
        (torch.Size([4, 100, 53]), torch.int64)
        >>> bool((data["true_switch"].sum(1) > 2).all())  # several sub-goals reached per trajectory
        True
    """
    from torchrl_options.envs.maps import load_map
    from torchrl_options.envs.supervisor import value_iteration

    grid = load_map(grid)
    subgoals = room_centers(grid) if subgoals is None else [tuple(int(v) for v in s) for s in subgoals]
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
