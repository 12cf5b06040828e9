"""A natively batched GridWorld environment: the four-, two- and three-rooms domains of the DDO paper.

Reference: R. Fox, S. Krishnan, I. Stoica, K. Goldberg, "Multi-Level Discovery of Deep Options",
arXiv:1703.08294 (2017), section 5.1 (four rooms, apple task) and appendix B (two rooms, start/goal task; three
rooms, two sub-goals).
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from torchrl_options.checks import check_bool, check_number
from torchrl_options.envs.maps import MOVES, GridMap, load_map

__all__ = ["GridWorldEnv", "TASKS"]

logger = logging.getLogger(__name__)

TASKS = ("apple", "goal", "subgoals")

# ------------------------------------------------------------------------------------------ counter-based RNG
# Each env owns a 32-bit key (from its seed) and a draw counter. The random numbers of one call (a step or a
# reset) are a hash of (key, counter, salt, stream): no generator state is shared between envs, so env i of a
# batch draws exactly what a lone env with the same key draws, whatever the batch size, and the whole batch is
# drawn with a handful of integer tensor ops. All arithmetic stays below 2**63 (no int64 overflow).
_M32 = 0xFFFFFFFF
_SALT_RESET = 0x2545F491
_SALT_STEP = 0x5851F42D


def _mul32(x: Tensor, c: int) -> Tensor:
    """``(x * c) mod 2**32`` for ``0 <= x < 2**32``, split in 16-bit halves so that int64 never overflows."""
    return (x * (c & 0xFFFF) + (((x * (c >> 16)) & 0xFFFF) << 16)) & _M32


def _mix32(x: Tensor) -> Tensor:
    """A 32-bit integer hash with good avalanche (xor-shift / multiply, "lowbias32" constants)."""
    x = x ^ (x >> 16)
    x = _mul32(x, 0x7FEB352D)
    x = x ^ (x >> 15)
    x = _mul32(x, 0x846CA68B)
    return x ^ (x >> 16)


def _seed_keys(seed: int, n: int, device: torch.device | None) -> Tensor:
    """The 32-bit keys of envs seeded ``seed, seed + 1, ..., seed + n - 1``."""
    seeds = [seed + i for i in range(n)]
    lo = torch.tensor([s & _M32 for s in seeds], dtype=torch.long, device=device)
    hi = torch.tensor([(s >> 32) & _M32 for s in seeds], dtype=torch.long, device=device)
    return _mix32(lo ^ _mix32((hi + 0x632BE5AB) & _M32))


def _counter_uniforms(key: Tensor, counter: Tensor, salt: int, k: int) -> Tensor:
    """``[n, k]`` float32 uniforms in ``[0, 1)`` (24 bits) for keys ``[n]`` and counters ``[n]``."""
    base = _mix32(key ^ _mix32((counter ^ salt) & _M32))
    streams = torch.tensor([(j * 0x9E3779B9) & _M32 for j in range(k)], dtype=torch.long, device=key.device)
    bits = _mix32((base[:, None] + streams) & _M32)
    return (bits >> 8).to(torch.float32) * (2.0**-24)


def _floor_index(u: Tensor, size: Tensor | int) -> Tensor:
    """``floor(u * size)`` as long, clamped to ``size - 1`` (uniform over ``0..size-1`` for ``u ~ U[0, 1)``)."""
    size = torch.as_tensor(size, device=u.device)
    return torch.minimum((u * size).long(), size - 1)


def _as_position(pos: Any, grid: GridMap, what: str) -> tuple[int, int]:
    if isinstance(pos, Tensor):
        pos = pos.tolist()
    pos = tuple(int(v) for v in pos)
    if len(pos) != 2 or grid.is_wall(pos):
        raise ValueError(f"{what} must be a free cell (row, col) of map {grid.name!r}, got {pos}.")
    return pos


class GridWorldEnv(EnvBase):
    """A natively batched GridWorld: ``N`` independent grids stepped with one set of tensor ops.

    The agent moves up, right, down or left (actions 0-3, see :data:`~torchrl_options.envs.maps.ACTION_NAMES`);
    moving into a wall leaves it in place. With probability ``noise`` the chosen action is replaced by one drawn
    uniformly from the four (which may be the chosen one again, so the executed move differs from the chosen one
    with probability ``0.75 * noise``). This is the environment noise of the paper (0.3 in all its GridWorlds).

    Tasks:

    - ``"apple"`` (section 5.1): an apple lies in a random cell of a random room (room uniform, then cell
      uniform, never on the agent). Taking it gives +1 and the apple respawns the same way. A continuing task: it
      never terminates; episodes are truncated after ``max_steps`` steps. The agent starts in a uniformly random
      free cell (``start=None``), or at ``start``.
    - ``"goal"`` (appendix B, two rooms): +1 and termination on reaching the goal; truncation after
      ``max_steps`` (the paper's two-rooms RL task: ``max_steps=20``). By default start and goal are random cells of
      two different rooms; either can be fixed with ``start`` / ``goal`` (a ``(row, col)`` or ``"map"`` for the
      map's marker), the other is then drawn in another room.
    - ``"subgoals"`` (appendix B, three rooms): the agent must reach the sub-goals in order (by default the map's
      markers 3 then 4); each gives ``1 / K`` (0.5 for two) and only counts when reached in order; the episode
      terminates at the last one. ``"target_pos"`` is the current sub-goal and ``"stage"`` counts those reached.
      The agent starts at the map's start marker (the default when the map has one, or ``start="map"``) or, with
      ``start="random"``, in a random cell of room 0 (the leftmost room).

    Rooms come from the map (:func:`~torchrl_options.envs.maps.detect_rooms`: free areas at least two cells wide;
    the four 3x3 corner rooms of the four-rooms map).

    Keys (all with the env's batch size as leading dims):

    - ``"observation"``: float32. By default ``[4]``: ``(agent_row, agent_col, target_row, target_col)`` divided
      by ``(H - 1, W - 1)``, so in ``[0, 1]`` (the paper's networks take positions; normalised inputs suit small
      tanh MLPs). ``normalize=False`` gives raw coordinates. ``one_hot=True`` gives ``[2F]``: a one-hot of the
      agent's cell then of the target's cell over the ``F`` free cells (cell index: ``grid.cell_index``).
    - ``"agent_pos"``, ``"target_pos"``: long ``[2]`` ``(row, col)``; the target is the apple, the goal or the
      current sub-goal. These, with ``"step_count"`` (long ``[1]``, steps since reset) and, for ``"subgoals"``,
      ``"stage"`` (long ``[1]``), are the env's state: ``_step`` reads them from the input tensordict (the env is
      stateless apart from its random number generator), so writing them before :meth:`step` places the agent by
      hand (see also :meth:`reset_at`). ``"step_count"`` has the key and meaning of TorchRL's ``StepCounter``,
      so a ``StepCounter`` stacked on top counts the same steps.
    - ``"action"``: long, ``Categorical(4)``; ``"reward"`` float32 ``[1]``; ``"done"``, ``"terminated"``,
      ``"truncated"``: bool ``[1]``.

    Partial resets (``"_reset"``) and partial steps (``"_step"``) are honoured; envs that are not reset or stepped
    keep their state and do not consume random numbers.

    Randomness: every env draws from a counter-based generator keyed by its own seed. Env ``i`` (flat, row-major
    index) of a batch seeded with ``s`` (``env.set_seed(s)`` or ``seed=s``) behaves exactly like a lone env seeded
    with ``s + i``, given the same actions and resets, whatever the batch size. (A single ``torch.Generator`` would
    interleave the envs' draws, tying env ``i`` to the batch size; one generator per env would need a Python loop
    over envs.) Without a seed, the env draws one from torch's global generator, so ``torch.manual_seed`` makes it
    reproducible too.

    Args:
        grid (str, Path or GridMap): a built-in map name (``"four-rooms"``, ``"two-rooms"`` (10x20),
            ``"two-rooms-8x20"``, ``"three-rooms"`` (10x25)), a map file, or a :class:`GridMap`.
            Defaults to ``"four-rooms"``.
        task (str): ``"apple"`` (default), ``"goal"`` or ``"subgoals"``.

    Keyword Args:
        batch_size (int or sequence of int): the batch of independent grids. Defaults to ``()`` (one grid, no
            batch dimension); use ``[N]`` for ``N`` grids.
        noise (float): probability of replacing the chosen action by a uniformly random one. Defaults to 0.3.
        max_steps (int, optional): truncation horizon (``"truncated"`` is set when ``step_count`` reaches it);
            ``None`` never truncates. Defaults to 100: our choice for the four-rooms DQN episodes (the paper does
            not state it); use 1000 for the paper's demonstrations and 20 for the two-rooms task.
        start: ``None`` (the task's default, see above), ``"random"`` (the task's random rule, see above),
            ``"map"`` (the map's start marker) or a ``(row, col)``.
        goal: ``"goal"`` task only: ``None`` or ``"random"`` (a random cell of a room other than the start's),
            ``"map"`` (the map's goal marker) or a ``(row, col)``.
        subgoals (sequence of (row, col), optional): ``"subgoals"`` task only; defaults to the map's goal markers.
        one_hot (bool): one-hot observation (see above). Defaults to ``False``.
        normalize (bool): scale positions to ``[0, 1]`` (ignored with ``one_hot``). Defaults to ``True``.
        seed (int, optional): seed of env 0 (env ``i`` gets ``seed + i``).
        device: the device of the env's tensors.

    Examples:
        >>> env = GridWorldEnv("four-rooms", batch_size=[8], seed=0)
        >>> td = env.rollout(5)
        >>> td.shape, td["observation"].shape, td["action"].dtype
        (torch.Size([8, 5]), torch.Size([8, 5, 4]), torch.int64)
        >>> from torchrl.envs.utils import check_env_specs
        >>> check_env_specs(GridWorldEnv("two-rooms", task="goal", max_steps=20, batch_size=[4]))
        >>> env = GridWorldEnv("three-rooms", task="subgoals", one_hot=True, seed=1)
        >>> env.reset()["observation"].shape  # two one-hots over the 156 free cells
        torch.Size([312])
        >>> env.render().shape  # an RGB picture, 24 pixels per cell
        (240, 600, 3)
    """

    def __init__(
        self,
        grid: str | Path | GridMap = "four-rooms",
        task: str = "apple",
        *,
        batch_size: int | Sequence[int] | torch.Size = (),
        noise: float = 0.3,
        max_steps: int | None = 100,
        start: str | Sequence[int] | None = None,
        goal: str | Sequence[int] | None = None,
        subgoals: Sequence[Sequence[int]] | None = None,
        one_hot: bool = False,
        normalize: bool = True,
        seed: int | None = None,
        device: torch.device | str | None = None,
    ) -> None:
        self._init_kwargs = dict(
            grid=grid, task=task, batch_size=batch_size, noise=noise, max_steps=max_steps, start=start, goal=goal,
            subgoals=subgoals, one_hot=one_hot, normalize=normalize, seed=seed, device=device,
        )  # fmt: skip
        if isinstance(batch_size, int):
            batch_size = (batch_size,)
        if not isinstance(batch_size, (tuple, list, torch.Size)) or any(
            isinstance(b, bool) or not isinstance(b, int) or b < 1 for b in batch_size
        ):
            raise ValueError(f"batch_size must be an int >= 1 or a sequence of them (or []), got {batch_size!r}.")
        super().__init__(device=device, batch_size=torch.Size(batch_size))
        self.grid = load_map(grid)
        if task not in TASKS:
            raise ValueError(f"task must be one of {TASKS}, got {task!r}.")
        check_number(noise, "noise", lo=0.0, hi=1.0)
        if max_steps is not None and (isinstance(max_steps, bool) or not isinstance(max_steps, int) or max_steps < 1):
            raise ValueError(f"max_steps must be a positive int or None, got {max_steps}.")
        for name, flag in (("one_hot", one_hot), ("normalize", normalize)):
            check_bool(flag, name)
        self.task = task
        self.noise = float(noise)
        self.max_steps = max_steps
        self.one_hot = one_hot
        self.normalize = normalize
        self._n = int(math.prod(self.batch_size))
        self._configure_task(start, goal, subgoals)
        self._register_tables()
        self._make_specs()
        self.register_buffer("_rng_key", torch.zeros(self._n, dtype=torch.long, device=self.device))
        self.register_buffer("_rng_counter", torch.zeros(self._n, dtype=torch.long, device=self.device))
        if seed is None:
            seed = int(torch.randint(0, 2**62, ()).item())
        self._set_seed(seed)
        self._last_state: tuple[Tensor, Tensor] | None = None

    # --------------------------------------------------------------------------------------------- set-up
    def _configure_task(self, start, goal, subgoals) -> None:
        grid = self.grid

        def resolve(pos, what: str, marker: tuple[int, int] | None):
            if pos is None or (isinstance(pos, str) and pos == "random"):
                return None
            if isinstance(pos, str):
                if pos != "map":
                    raise ValueError(f"{what} must be None, 'random', 'map' or a (row, col), got {pos!r}.")
                if marker is None:
                    raise ValueError(f"{what}='map' but map {grid.name!r} has no such marker.")
                return marker
            return _as_position(pos, grid, what)

        if self.task == "subgoals" and start is None and grid.start is not None:
            start = "map"
        self._start = resolve(start, "start", grid.start)
        self._goal = None
        self._subgoals: tuple[tuple[int, int], ...] = ()
        needs_rooms = 0
        if self.task == "apple":
            if goal is not None or subgoals is not None:
                raise ValueError("The apple task takes no goal or subgoals.")
            needs_rooms = 1
            if any(len(cells) < 2 for cells in grid.room_cells):
                raise ValueError("The apple task needs rooms of at least two cells.")
        elif self.task == "goal":
            if subgoals is not None:
                raise ValueError("task='goal' takes goal=..., not subgoals.")
            self._goal = resolve(goal, "goal", grid.goals[0] if grid.goals else None)
            if self._start is None or self._goal is None:
                needs_rooms = 2 if self._start is None and self._goal is None else 1
            if self._start is not None and self._start == self._goal:
                raise ValueError(f"start and goal are the same cell {self._start}.")
        else:
            if goal is not None:
                raise ValueError("task='subgoals' takes subgoals=..., not goal.")
            subgoals = grid.goals if subgoals is None else subgoals
            self._subgoals = tuple(_as_position(p, grid, "subgoal") for p in subgoals)
            if not self._subgoals:
                raise ValueError(f"task='subgoals' needs sub-goals: map {grid.name!r} has no goal markers.")
            if self._start is None:
                needs_rooms = 1
        if grid.num_rooms < needs_rooms:
            raise ValueError(f"Map {grid.name!r} has {grid.num_rooms} room(s); task {self.task!r} needs rooms.")
        if self.task == "goal" and needs_rooms and grid.num_rooms < 2:
            raise ValueError("A random start or goal is drawn in another room: the map needs two rooms.")

    def _register_tables(self) -> None:
        grid, device = self.grid, self.device
        R = grid.num_rooms
        sizes = [len(cells) for cells in grid.room_cells]
        table = torch.zeros(max(R, 1), max(sizes, default=1), dtype=torch.long)
        rank = torch.zeros(grid.num_free, dtype=torch.long)
        for r, cells in enumerate(grid.room_cells):
            table[r, : len(cells)] = cells
            rank[cells] = torch.arange(len(cells))
        H, W = grid.shape
        buffers = {
            "_walls": grid.walls,
            "_cell_index": grid.cell_index,
            "_free_cells": grid.free_cells,
            "_moves": MOVES,
            "_room_table": table,
            "_room_sizes": torch.tensor(sizes or [1], dtype=torch.long),
            "_cell_room": grid.cell_room,
            "_cell_rank": rank,
            "_scale": torch.tensor([max(H - 1, 1), max(W - 1, 1)] * 2, dtype=torch.float32),
            "_subgoal_table": torch.tensor(self._subgoals or [[0, 0]], dtype=torch.long),
        }
        for name, value in buffers.items():
            self.register_buffer(name, value.to(device))

    def _make_specs(self) -> None:
        bs, device = self.batch_size, self.device
        H, W = self.grid.shape
        obs_dim = 2 * self.grid.num_free if self.one_hot else 4
        if self.one_hot or self.normalize:
            obs_spec = Bounded(0.0, 1.0, shape=(*bs, obs_dim), dtype=torch.float32, device=device)
        else:
            obs_spec = Unbounded(shape=(*bs, obs_dim), dtype=torch.float32, device=device)
        high = torch.tensor([H - 1, W - 1], dtype=torch.long, device=device).expand(*bs, 2)

        def pos_spec() -> Bounded:
            return Bounded(torch.zeros_like(high), high.clone(), shape=(*bs, 2), dtype=torch.long, device=device)

        observation = dict(
            observation=obs_spec,
            agent_pos=pos_spec(),
            target_pos=pos_spec(),
            step_count=Unbounded(shape=(*bs, 1), dtype=torch.long, device=device),
        )
        if self.task == "subgoals":
            observation["stage"] = Bounded(
                0, len(self._subgoals), shape=(*bs, 1), dtype=torch.long, device=device
            )
        self.observation_spec = Composite(**observation, shape=bs, device=device)
        self.action_spec = Categorical(4, shape=bs, device=device)
        self.reward_spec = Unbounded(shape=(*bs, 1), dtype=torch.float32, device=device)
        done = Categorical(2, shape=(*bs, 1), dtype=torch.bool, device=device)
        self.done_spec = Composite(done=done, terminated=done.clone(), truncated=done.clone(), shape=bs, device=device)

    # -------------------------------------------------------------------------------------------- helpers
    def _set_seed(self, seed: int | None) -> None:
        if seed is None:
            return
        self._rng_key.copy_(_seed_keys(int(seed), self._n, self.device))
        self._rng_counter.zero_()

    def _uniforms(self, active: Tensor, salt: int, k: int) -> Tensor:
        """``[n, k]`` uniforms for this call; the counters of ``active`` envs move on."""
        u = _counter_uniforms(self._rng_key, self._rng_counter, salt, k)
        self._rng_counter.add_(active.long())
        return u

    def _flat_mask(self, tensordict: TensorDictBase | None, key: NestedKey) -> Tensor:
        mask = None if tensordict is None else tensordict.get(key, None)
        if mask is None:
            return torch.ones(self._n, dtype=torch.bool, device=self.device)
        return mask.reshape(self._n, -1).any(-1)

    def _flat(self, tensordict: TensorDictBase, key: NestedKey, last: int) -> Tensor:
        return tensordict.get(key).reshape(self._n, last)

    def _positions(self, cells: Tensor) -> Tensor:
        return self._free_cells[cells]

    def _cells(self, positions: Tensor) -> Tensor:
        return self._cell_index[positions[:, 0], positions[:, 1]]

    def _sample_room(self, u: Tensor, excluded_room: Tensor) -> Tensor:
        """A uniform room, other than ``excluded_room`` where that is ``>= 0``."""
        R = self.grid.num_rooms
        excl = excluded_room >= 0
        room = _floor_index(u, R - excl.long())
        return room + (excl & (room >= excluded_room)).long()

    def _sample_cell_in_room(self, u: Tensor, room: Tensor, excluded_cell: Tensor | None = None) -> Tensor:
        """A uniform cell of ``room``, other than ``excluded_cell`` (cell indices, ``[n]``)."""
        size = self._room_sizes[room]
        if excluded_cell is None:
            return self._room_table[room, _floor_index(u, size)]
        excl = self._cell_room[excluded_cell] == room
        k = _floor_index(u, size - excl.long())
        k = k + (excl & (k >= self._cell_rank[excluded_cell])).long()
        return self._room_table[room, k]

    def _fixed(self, pos: tuple[int, int]) -> Tensor:
        return torch.tensor(pos, dtype=torch.long, device=self.device).expand(self._n, 2)

    def _sample_episode(self, u: Tensor) -> tuple[Tensor, Tensor]:
        """Start and target positions ``[n, 2]`` of new episodes, from uniforms ``u`` ``[n, 4]``."""
        n, device = self._n, self.device
        no_room = torch.full((n,), -1, dtype=torch.long, device=device)
        if self.task == "apple":
            if self._start is None:
                agent_cell = _floor_index(u[:, 0], self.grid.num_free)
            else:
                agent_cell = self._cells(self._fixed(self._start))
            room = self._sample_room(u[:, 2], no_room)
            target_cell = self._sample_cell_in_room(u[:, 3], room, excluded_cell=agent_cell)
            return self._positions(agent_cell), self._positions(target_cell)
        if self.task == "subgoals":
            if self._start is None:
                agent_cell = self._sample_cell_in_room(u[:, 1], torch.zeros_like(no_room))
                agent = self._positions(agent_cell)
            else:
                agent = self._fixed(self._start)
            return agent, self._subgoal_table[0].expand(n, 2)
        # goal task: whichever of start / goal is random goes in a room other than the other's
        if self._start is not None:
            agent = self._fixed(self._start)
        else:
            goal_room = no_room if self._goal is None else self._cell_room[self._cells(self._fixed(self._goal))]
            room = self._sample_room(u[:, 0], goal_room)
            agent = self._positions(self._sample_cell_in_room(u[:, 1], room))
        if self._goal is not None:
            goal = self._fixed(self._goal)
        else:
            room = self._sample_room(u[:, 2], self._cell_room[self._cells(agent)])
            goal = self._positions(self._sample_cell_in_room(u[:, 3], room))
        return agent, goal

    def _observe(self, agent: Tensor, target: Tensor) -> Tensor:
        if self.one_hot:
            F = self.grid.num_free
            obs = torch.zeros(self._n, 2 * F, dtype=torch.float32, device=self.device)
            obs.scatter_(1, torch.stack([self._cells(agent), F + self._cells(target)], -1), 1.0)
            return obs
        obs = torch.cat([agent, target], -1).to(torch.float32)
        return obs / self._scale if self.normalize else obs

    def _output(self, agent: Tensor, target: Tensor, count: Tensor, stage: Tensor, **extra: Tensor) -> TensorDict:
        bs = self.batch_size
        out = {
            "observation": self._observe(agent, target).reshape(*bs, -1),
            "agent_pos": agent.reshape(*bs, 2),
            "target_pos": target.reshape(*bs, 2),
            "step_count": count.reshape(*bs, 1),
        }
        if self.task == "subgoals":
            out["stage"] = stage.reshape(*bs, 1)
        out.update({key: value.reshape(*bs, 1) for key, value in extra.items()})
        self._last_state = (out["agent_pos"], out["target_pos"])
        return TensorDict(out, batch_size=bs, device=self.device)

    # ------------------------------------------------------------------------------------------ reset/step
    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        # Fresh values for every env; TorchRL keeps the old values of envs not flagged by "_reset". Only the
        # flagged envs consume random numbers.
        reset = self._flat_mask(tensordict, "_reset")
        agent, target = self._sample_episode(self._uniforms(reset, _SALT_RESET, 4))
        zeros = torch.zeros(self._n, dtype=torch.long, device=self.device)
        false = torch.zeros(self._n, dtype=torch.bool, device=self.device)
        return self._output(agent, target, zeros, zeros, done=false, terminated=false, truncated=false)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        n = self._n
        active = self._flat_mask(tensordict, "_step")
        agent = self._flat(tensordict, "agent_pos", 2)
        target = self._flat(tensordict, "target_pos", 2)
        count = self._flat(tensordict, "step_count", 1).squeeze(-1)
        action = self._flat(tensordict, self.action_key, 1).squeeze(-1).long()
        u = self._uniforms(active, _SALT_STEP, 4)

        replaced = u[:, 0] < self.noise
        executed = torch.where(replaced, _floor_index(u[:, 1], 4), action)
        H, W = self.grid.shape
        moved = agent + self._moves[executed]
        moved = torch.stack([moved[:, 0].clamp(0, H - 1), moved[:, 1].clamp(0, W - 1)], -1)
        blocked = self._walls[moved[:, 0], moved[:, 1]]
        agent_next = torch.where((blocked | ~active)[:, None], agent, moved)
        reached = (agent_next == target).all(-1) & active

        stage = torch.zeros(n, dtype=torch.long, device=self.device)
        if self.task == "apple":
            room = self._sample_room(u[:, 2], torch.full_like(stage, -1))
            apple = self._positions(self._sample_cell_in_room(u[:, 3], room, self._cells(agent_next)))
            target_next = torch.where(reached[:, None], apple, target)
            reward = reached.to(torch.float32)
            terminated = torch.zeros_like(reached)
        elif self.task == "goal":
            target_next = target
            reward = reached.to(torch.float32)
            terminated = reached
        else:
            K = len(self._subgoals)
            stage = self._flat(tensordict, "stage", 1).squeeze(-1)
            reward = reached.to(torch.float32) / K
            stage = stage + reached.long()
            terminated = stage >= K
            target_next = self._subgoal_table[stage.clamp(max=K - 1)]

        count = count + active.long()
        truncated = count >= self.max_steps if self.max_steps is not None else torch.zeros_like(reached)
        # envs left out of a partial step keep their done flags
        previous = {k: tensordict.get(k, None) for k in ("terminated", "truncated")}
        if previous["terminated"] is not None:
            terminated = torch.where(active, terminated, previous["terminated"].reshape(n))
        if previous["truncated"] is not None:
            truncated = torch.where(active, truncated, previous["truncated"].reshape(n))
        return self._output(
            agent_next, target_next, count, stage,
            reward=reward, done=terminated | truncated, terminated=terminated, truncated=truncated,
        )  # fmt: skip

    # ----------------------------------------------------------------------------------------- utilities
    def reset_at(
        self,
        agent_pos: Sequence[int] | Tensor | None = None,
        target_pos: Sequence[int] | Tensor | None = None,
        *,
        stage: int | Tensor | None = None,
    ) -> TensorDictBase:
        """Resets all envs, then places the agent and/or target by hand.

        Positions broadcast to ``[*batch_size, 2]``; the observation is recomputed. For ``"subgoals"``, ``stage``
        sets the sub-goals already reached (and the target to the next one unless ``target_pos`` is given).

        Examples:
            >>> env = GridWorldEnv("four-rooms", noise=0.0, seed=0)
            >>> td = env.reset_at(agent_pos=(1, 1), target_pos=(2, 1))
            >>> td["action"] = torch.tensor(2)  # down, onto the apple
            >>> env.step(td)["next", "reward"]
            tensor([1.])
        """
        td = self.reset()
        n, bs = self._n, self.batch_size
        agent = self._flat(td, "agent_pos", 2)
        target = self._flat(td, "target_pos", 2)
        stages = torch.zeros(n, dtype=torch.long, device=self.device)
        if stage is not None:
            if self.task != "subgoals":
                raise ValueError("stage is for the 'subgoals' task.")
            stages = torch.as_tensor(stage, dtype=torch.long, device=self.device).expand(bs).reshape(n)
            if ((stages < 0) | (stages >= len(self._subgoals))).any():
                raise ValueError(f"stage must be in [0, {len(self._subgoals) - 1}].")
            target = self._subgoal_table[stages]
        for name, value in (("agent_pos", agent_pos), ("target_pos", target_pos)):
            if value is None:
                continue
            value = torch.as_tensor(value, dtype=torch.long, device=self.device).expand(*bs, 2).reshape(n, 2)
            H, W = self.grid.shape
            inside = (value >= 0).all() and (value[:, 0] < H).all() and (value[:, 1] < W).all()
            if not inside or self._walls[value[:, 0], value[:, 1]].any():
                raise ValueError(f"{name} must be free cells of the map.")
            if name == "agent_pos":
                agent = value
            else:
                target = value
        out = self._output(agent, target, stages.new_zeros(n), stages)
        td.update(out)
        return td

    def replace(self, **overrides: Any) -> GridWorldEnv:
        """A new env with this env's constructor arguments, except ``overrides``.

        Examples:
            >>> env = GridWorldEnv("two-rooms", task="goal", max_steps=20)
            >>> env.replace(batch_size=[16], noise=0.0).batch_size
            torch.Size([16])
        """
        return type(self)(**{**self._init_kwargs, "noise": self.noise, **overrides})

    @property
    def num_actions(self) -> int:
        """The number of primitive actions (4)."""
        return 4

    @property
    def subgoals(self) -> tuple[tuple[int, int], ...]:
        """The sub-goals of the ``"subgoals"`` task (empty otherwise)."""
        return self._subgoals

    def render(
        self,
        tensordict: TensorDictBase | None = None,
        index: int | Sequence[int] = 0,
        **kwargs: Any,
    ) -> np.ndarray:
        """An RGB picture (``uint8 [H * cell_size, W * cell_size, 3]``) of one env of the batch.

        Args:
            tensordict: a tensordict with ``"agent_pos"`` and ``"target_pos"`` (batched like the env); defaults to
                the state of the last reset or step.
            index: the env to draw, an int (flat index) or a tuple of batch indices.
            **kwargs: passed to :func:`~torchrl_options.envs.render.render_grid` (``cell_size``, ``heatmap``,
                ``trajectories``, ...).

        Examples:
            >>> env = GridWorldEnv(batch_size=[2], seed=0)
            >>> _ = env.reset()
            >>> image = env.render(index=1, cell_size=10)
            >>> image.shape, image.dtype
            ((150, 110, 3), dtype('uint8'))
        """
        from torchrl_options.envs.render import render_grid

        if tensordict is not None:
            agent, target = tensordict.get("agent_pos"), tensordict.get("target_pos")
        elif self._last_state is not None:
            agent, target = self._last_state
        else:
            agent = target = None
        if agent is not None:
            if isinstance(index, int):
                agent, target = agent.reshape(-1, 2)[index], target.reshape(-1, 2)[index]
            else:
                agent, target = agent[tuple(index)], target[tuple(index)]
        kwargs.setdefault("target_kind", "apple" if self.task == "apple" else "goal")
        return render_grid(self.grid, agent_pos=agent, target_pos=target, **kwargs)
