"""A value-iteration supervisor for the GridWorlds, and the demonstrations it gives DDO.

Reference: R. Fox, S. Krishnan, I. Stoica, K. Goldberg, "Multi-Level Discovery of Deep Options",
arXiv:1703.08294 (2017): section 5.1 ("We use Value Iteration to compute the optimal policy, and then use this
policy as a supervisor to generate 50 trajectories of length 1000") and appendix B (figure 8: environment noise
and supervisor noise).
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict import pad as td_pad
from tensordict.nn import TensorDictModuleBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.envs.utils import step_mdp

from torchrl_options.checks import check_distinct_keys, check_int, check_number
from torchrl_options.envs.gridworld import GridWorldEnv
from torchrl_options.envs.maps import GridMap, load_map

__all__ = ["ValueIterationSupervisor", "generate_demonstrations", "value_iteration"]

logger = logging.getLogger(__name__)


def value_iteration(
    grid: GridMap | str,
    noise: float = 0.3,
    *,
    tol: float = 1e-9,
    max_iterations: int = 100_000,
    dtype: torch.dtype = torch.float64,
) -> tuple[Tensor, Tensor]:
    """Expected number of steps to reach each cell from each cell, under the optimal policy and action noise.

    Value iteration on the stochastic-shortest-path problem "reach cell ``g``", for every target ``g`` at once:

    .. math::

        V_g(g) = 0, \\qquad V_g(s) = \\min_a Q_g(s, a), \\qquad
        Q_g(s, a) = 1 + (1 - \\epsilon) V_g(s'_a) + \\frac{\\epsilon}{4} \\sum_{a'} V_g(s'_{a'}),

    where ``s'_a`` is the cell reached from ``s`` by move ``a`` (``s`` itself when a wall blocks it) and
    ``epsilon`` is the probability that the env replaces the chosen action by a uniformly random one. A table of
    ``[F, F]`` values (``F`` free cells; about 50-150 for the paper's maps) is updated with tensor ops until the
    largest change is below ``tol``. With ``noise=0`` the values are the shortest-path lengths. Unreachable
    pairs get ``inf``.

    Args:
        grid: a map or map name.
        noise (float): the env's action noise ``epsilon`` in ``[0, 1)``.
        tol (float): convergence threshold on the largest value change.
        max_iterations (int): a cap on sweeps (a warning is logged if reached).
        dtype: floating dtype of the tables.

    Returns:
        ``(values, q_values)``: ``[F, F]`` ``values[g, s]`` and ``[F, F, 4]`` ``q_values[g, s, a]``, indexed by
        cell index (target first).

    Examples:
        >>> from torchrl_options.envs.maps import parse_map
        >>> corridor = parse_map("1 1 1 1 1\\n1 0 0 0 1\\n1 1 1 1 1")
        >>> values, q = value_iteration(corridor, noise=0.0)
        >>> values
        tensor([[0., 1., 2.],
                [1., 0., 1.],
                [2., 1., 0.]], dtype=torch.float64)
        >>> q[2, 0]  # from the left end towards the right end: up, right, down, left
        tensor([3., 2., 3., 3.], dtype=torch.float64)
    """
    grid = load_map(grid)
    check_number(noise, "noise", lo=0.0, hi=1.0, hi_open=True)
    check_number(tol, "tol", lo=0.0, hi=math.inf, hi_open=True)
    check_int(max_iterations, "max_iterations", minimum=1)
    nxt = grid.next_cell  # [F, 4]
    F = grid.num_free
    is_target = torch.eye(F, dtype=torch.bool)
    # reachability closure, so that unreachable pairs (which would grow forever) are set to inf
    reach = is_target.clone()
    while True:
        grown = reach | reach[:, nxt].any(-1)
        if torch.equal(grown, reach):
            break
        reach = grown
    values = torch.zeros(F, F, dtype=dtype)
    for iteration in range(max_iterations):
        q = _q_values(values, nxt, noise)
        new = torch.where(is_target | ~reach, 0.0, q.min(-1).values)
        delta = (new - values).abs().max().item()
        values = new
        if delta <= tol:
            break
    else:
        logger.warning("value_iteration: no convergence after %d sweeps (last change %.3g).", max_iterations, delta)
    logger.debug("value_iteration: %d sweeps, noise %.3g", iteration + 1, noise)
    values = values.masked_fill(~reach, float("inf"))
    return values, _q_values(values.masked_fill(~reach, 0.0), nxt, noise).masked_fill(~reach[..., None], float("inf"))


def _q_values(values: Tensor, nxt: Tensor, noise: float) -> Tensor:
    successors = values[:, nxt]  # [G, F, 4]
    return 1.0 + (1.0 - noise) * successors + noise * successors.mean(-1, keepdim=True)


class ValueIterationSupervisor(TensorDictModuleBase):
    """The optimal GridWorld policy from :func:`value_iteration`, as a TorchRL policy.

    It reads the agent's and the target's positions and writes the action: an optimal action towards the
    target (the apple, the goal or the current sub-goal), ties broken uniformly at random (``tie_break="random"``)
    or by the lowest action index (``"first"``). With probability ``supervisor_noise`` it writes a uniformly random
    action instead: the "supervisor noise" of the paper's figure 8b (the environment's own noise, figure 8a, is
    the env's ``noise``). The values account for the env's noise; with uniform replacement noise the optimal
    actions are those leading to the successor of smallest value.

    Args:
        grid: a :class:`~torchrl_options.envs.GridWorldEnv` (its map, noise and device are used), a map or a map
            name.
        noise (float, optional): the env's action noise; defaults to the env's, or 0.3 for a map.
        supervisor_noise (float): probability of a uniformly random action. Defaults to 0.
        tie_break (str): ``"random"`` (default) or ``"first"``.
        seed (int, optional): seed of the supervisor's own ``torch.Generator`` (tie breaks, supervisor noise).
        agent_key, target_key, action_key (NestedKey): the keys read and written.
        device: defaults to the env's device, else the CPU.

    Attributes:
        values (Tensor): ``[F, F]`` expected steps, ``values[target_cell, agent_cell]``.
        q_values (Tensor): ``[F, F, 4]``.
        optimal (Tensor): ``[F, F, 4]`` bool, the optimal actions.

    Examples:
        >>> env = GridWorldEnv("four-rooms", batch_size=[4], max_steps=1000, seed=0)
        >>> supervisor = ValueIterationSupervisor(env, seed=0)
        >>> td = env.rollout(1000, supervisor)
        >>> bool(td["next", "reward"].sum(1).min() > 30)  # every env takes many apples
        True
        >>> round(float(supervisor.value(torch.tensor([1, 1]), torch.tensor([13, 9]))), 1)  # expected steps
        28.6
    """

    def __init__(
        self,
        grid: GridWorldEnv | GridMap | str,
        noise: float | None = None,
        supervisor_noise: float = 0.0,
        *,
        tie_break: str = "random",
        seed: int | None = None,
        agent_key: NestedKey = "agent_pos",
        target_key: NestedKey = "target_pos",
        action_key: NestedKey = "action",
        device: torch.device | str | None = None,
    ) -> None:
        super().__init__()
        if isinstance(grid, GridWorldEnv):
            noise = grid.noise if noise is None else noise
            device = grid.device if device is None else device
            grid = grid.grid
        self.grid = load_map(grid)
        check_number(noise, "noise", lo=0.0, hi=1.0, allow_none=True)
        self.noise = 0.3 if noise is None else float(noise)
        check_number(supervisor_noise, "supervisor_noise", lo=0.0, hi=1.0)
        check_distinct_keys({"agent_key": agent_key, "target_key": target_key, "action_key": action_key},
                            "ValueIterationSupervisor")  # fmt: skip
        if tie_break not in ("random", "first"):
            raise ValueError(f"tie_break must be 'random' or 'first', got {tie_break!r}.")
        self.supervisor_noise = float(supervisor_noise)
        self.tie_break = tie_break
        self.in_keys = [agent_key, target_key]
        self.out_keys = [action_key]
        device = torch.device("cpu") if device is None else torch.device(device)
        values, q = value_iteration(self.grid, self.noise)
        # an action is optimal when its successor has the smallest value; the tolerance absorbs rounding only
        best = q.min(-1, keepdim=True).values
        optimal = q <= best + 1e-7 * (1.0 + best.abs())
        self.register_buffer("values", values.to(device=device, dtype=torch.float32))
        self.register_buffer("q_values", q.to(device=device, dtype=torch.float32))
        self.register_buffer("optimal", optimal.to(device))
        self.register_buffer("_cell_index", self.grid.cell_index.to(device))
        self.generator = torch.Generator(device=device)
        self.generator.manual_seed(int(torch.randint(0, 2**62, ()).item()) if seed is None else seed)

    def _cells(self, pos: Tensor) -> Tensor:
        pos = pos.to(self._cell_index.device).long()
        cells = self._cell_index[pos[..., 0], pos[..., 1]]
        if (cells < 0).any():
            raise ValueError("ValueIterationSupervisor: a position is on a wall.")
        return cells

    def value(self, agent_pos: Tensor, target_pos: Tensor) -> Tensor:
        """Expected number of steps from ``agent_pos`` to ``target_pos`` (``[..., 2]`` each) acting optimally."""
        return self.values[self._cells(target_pos), self._cells(agent_pos)]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        agent_key, target_key = self.in_keys
        agent = self._cells(tensordict.get(agent_key))
        target = self._cells(tensordict.get(target_key))
        optimal = self.optimal[target, agent]  # [..., 4]
        if self.tie_break == "random":
            scores = torch.rand(optimal.shape, generator=self.generator, device=optimal.device) + optimal
        else:
            scores = optimal.to(torch.float32) - 1e-3 * torch.arange(4, device=optimal.device)
        action = scores.argmax(-1)
        if self.supervisor_noise > 0:
            flip = torch.rand(action.shape, generator=self.generator, device=action.device) < self.supervisor_noise
            random = torch.randint(0, 4, action.shape, generator=self.generator, device=action.device)
            action = torch.where(flip, random, action)
        tensordict.set(self.out_keys[0], action.to(tensordict.device or action.device))
        return tensordict


def generate_demonstrations(
    env_or_map: GridWorldEnv | GridMap | str | Path = "four-rooms",
    num_trajectories: int = 50,
    length: int = 1000,
    *,
    noise: float | None = None,
    supervisor_noise: float = 0.0,
    seed: int = 0,
    tie_break: str = "random",
    **env_kwargs: Any,
) -> TensorDict:
    """Demonstrations of the value-iteration supervisor, in TorchRL's trajectory layout.

    One row per episode: ``num_trajectories`` envs are run in one batch from fresh resets for ``length`` steps
    (the paper's four-rooms supervised setting: 50 trajectories of length 1000 of the apple task, noise 0.3).
    Episodes that end early (goal tasks) are padded with zeros after their last step, and
    ``("collector", "mask")`` marks the valid steps; apple episodes never end early (the env's ``max_steps`` is
    set to ``length``), so their mask is all ``True``.

    ``"action"`` is the action the supervisor *chose* (after supervisor noise), not the move the env executed after
    its own noise replaced it: DDO models the agent's choices, and the env's noise is part of the dynamics.

    Args:
        env_or_map: a :class:`~torchrl_options.envs.GridWorldEnv` whose settings are reused (map, task, start, goal,
            observation format, noise, device) with ``batch_size=[num_trajectories]``, ``max_steps=length`` and
            ``seed``; or a map / map name, for a new env (``task`` defaults to ``"apple"``).
        num_trajectories (int): the number of demonstrations.
        length (int): steps per demonstration (the padded length for early-ending episodes).
        noise (float, optional): the env's action noise (figure 8a); defaults to the env's, or 0.3 for a map.
        supervisor_noise (float): probability that the supervisor acts at random (figure 8b). Defaults to 0.
        seed (int): seeds the env (env ``i`` gets ``seed + i``) and the supervisor.
        tie_break (str): see :class:`ValueIterationSupervisor`.
        **env_kwargs: other :class:`~torchrl_options.envs.GridWorldEnv` arguments (``task``, ``start``, ``goal``,
            ``one_hot``, ``max_steps`` (at most ``length``), ...).

    Returns:
        A TensorDict ``[num_trajectories, length]`` with ``"observation"``, ``"agent_pos"``, ``"target_pos"``,
        ``"step_count"``, ``"action"`` (long), ``"done"``/``"terminated"``/``"truncated"``, ``("next", ...)``
        with the same observation keys, ``"reward"``, ``"done"``, ``"terminated"``, ``"truncated"``, and
        ``("collector", "mask")`` (bool) and ``("collector", "traj_ids")`` (long, the row index).

    Examples:
        >>> demos = generate_demonstrations("four-rooms", num_trajectories=5, length=200, seed=0)
        >>> demos.shape, demos["action"].dtype, bool(demos["collector", "mask"].all())
        (torch.Size([5, 200]), torch.int64, True)
        >>> demos = generate_demonstrations("two-rooms", 10, 100, task="goal", seed=0)  # appendix B
        >>> lengths = demos["collector", "mask"].sum(-1)  # each episode ends at its goal, then padding
        >>> bool((lengths < 100).all()), bool((demos["next", "reward"].sum((1, 2)) == 1).all())
        (True, True)
    """
    check_int(num_trajectories, "num_trajectories", minimum=1)
    check_int(length, "length", minimum=1)
    check_number(noise, "noise", lo=0.0, hi=1.0, allow_none=True)
    if isinstance(env_or_map, GridWorldEnv):
        overrides = dict(env_kwargs)
        if noise is not None:
            overrides["noise"] = noise
        template = env_or_map
    else:
        template = None
        overrides = dict(grid=env_or_map, noise=0.3 if noise is None else noise, **env_kwargs)
    max_steps = overrides.pop("max_steps", length)
    if max_steps is None or max_steps > length:
        max_steps = length
    overrides.update(batch_size=[num_trajectories], max_steps=max_steps, seed=seed)
    env = template.replace(**overrides) if template is not None else GridWorldEnv(**overrides)
    supervisor = ValueIterationSupervisor(env, supervisor_noise=supervisor_noise, tie_break=tie_break, seed=seed)

    # A plain loop rather than env.rollout: it stops as soon as every row has finished its first episode, and
    # never resets (each row is one episode).
    steps = []
    finished = torch.zeros(num_trajectories, dtype=torch.bool, device=env.device)
    td = env.reset()
    with torch.no_grad():
        for _ in range(length):
            td = env.step(supervisor(td))
            steps.append(td)
            finished |= td.get(("next", "done")).reshape(num_trajectories)
            if finished.all():
                break
            td = step_mdp(td, keep_other=False, exclude_action=True)
    data = torch.stack(steps, dim=1)
    done = data.get(("next", "done")).reshape(num_trajectories, -1)
    valid = (done.long().cumsum(-1) - done.long()) == 0  # up to and including the first done step
    data = data.apply(lambda x: x.masked_fill(~valid.reshape(*valid.shape, *[1] * (x.ndim - 2)), 0))
    data.set(("collector", "mask"), valid)
    if data.shape[1] < length:
        data = td_pad(data, [0, 0, 0, length - data.shape[1]])
    traj_ids = torch.arange(num_trajectories, device=data.device)[:, None].expand(num_trajectories, length)
    data.set(("collector", "traj_ids"), traj_ids.clone())
    logger.info(
        "generate_demonstrations: %d x %d steps on %r (task %s, noise %.2f, supervisor noise %.2f), %d valid",
        num_trajectories, length, env.grid.name, env.task, env.noise, supervisor_noise, int(valid.sum()),
    )  # fmt: skip
    return data
