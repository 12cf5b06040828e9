"""Pictures of discovered options, like figures 1 and 6 of Fox et al. (2017), "Multi-Level Discovery of Deep Options".

Figure 1 draws each option's trajectories from random initial states until it terminates, one colour per option;
figure 6 draws an option's termination probability over the grid in red. :func:`draw_options` puts both in one
PNG: a first panel with every option's trajectories, then one panel per option with its termination probability
``sigmoid(termination_logits)`` at every free cell (for a fixed target) under its own trajectories.
"""
from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import cv2
import numpy as np
import torch
from tensordict.nn import TensorDictModuleBase
from torch import Tensor

from torchrl_options.envs import draw_trajectory, GridWorldEnv, option_colors, render_grid

__all__ = ["termination_map", "option_trajectories", "draw_options", "hierarchy_trajectories", "draw_hierarchy"]


def _env(env: GridWorldEnv | Mapping[str, Any], batch: int, seed: int) -> GridWorldEnv:
    if isinstance(env, GridWorldEnv):
        return env.replace(batch_size=[batch], seed=seed, max_steps=None)
    kwargs = {k: v for k, v in dict(env).items() if v is not None and k != "max_steps"}
    return GridWorldEnv(**kwargs, batch_size=[batch], seed=seed, max_steps=None)


def _target(env: GridWorldEnv, target_pos: Sequence[int] | None) -> tuple[int, int]:
    if target_pos is not None:
        return tuple(int(v) for v in target_pos)
    if env.subgoals:
        return env.subgoals[0]
    if env.grid.goals:
        return env.grid.goals[0]
    cells = env.grid.free_cells
    return tuple(int(v) for v in cells[len(cells) // 2])


@torch.no_grad()
def termination_map(
    options: TensorDictModuleBase, env: GridWorldEnv | Mapping[str, Any], target_pos: Sequence[int] | None = None
) -> Tensor:
    """``[K, F]`` termination probability of each option with the agent at each free cell, the target fixed.

    Examples:
        >>> from torchrl_options import OptionsMLP
        >>> env = GridWorldEnv("two-rooms", task="goal")
        >>> termination_map(OptionsMLP(4, 4, 2), env).shape  # 2 options, 88 free cells
        torch.Size([2, 88])
    """
    probe = env if isinstance(env, GridWorldEnv) else _env(env, 1, 0)
    free = probe.grid.free_cells
    batched = _env(probe, len(free), 0)
    td = batched.reset_at(agent_pos=free, target_pos=_target(probe, target_pos))
    return torch.sigmoid(options(td)["termination_logits"]).T.contiguous()


@torch.no_grad()
def option_trajectories(
    options: TensorDictModuleBase,
    env: GridWorldEnv | Mapping[str, Any],
    *,
    num_starts: int = 3,
    max_length: int = 30,
    target_pos: Sequence[int] | None = None,
    seed: int = 0,
) -> list[list[np.ndarray]]:
    """Trajectories ``[T, 2]`` of each option from ``num_starts`` random free cells, run until it terminates.

    An option acts (sampling its control policy) from a uniformly random start, with the target fixed, until its
    termination (drawn at each state it lands in), the episode's end or ``max_length`` steps. Returns a list per
    option of ``num_starts`` position arrays.

    Examples:
        >>> from torchrl_options import OptionsMLP
        >>> paths = option_trajectories(OptionsMLP(4, 4, 2), {"grid": "four-rooms"}, num_starts=2, max_length=5)
        >>> len(paths), len(paths[0]), paths[0][0].shape[1]
        (2, 2, 2)
    """
    probe = env if isinstance(env, GridWorldEnv) else _env(env, 1, seed)
    K = int(options.num_options)
    n = K * num_starts
    batched = _env(probe, n, seed)
    generator = torch.Generator().manual_seed(seed)
    free = batched.grid.free_cells
    starts = free[torch.randint(0, len(free), (n,), generator=generator)]
    target = _target(probe, target_pos)
    td = batched.reset_at(agent_pos=starts, target_pos=target)
    which = torch.arange(K).repeat_interleave(num_starts)
    rows = torch.arange(n)
    positions = [td["agent_pos"].clone()]
    alive = torch.ones(n, dtype=torch.bool)
    lengths = torch.ones(n, dtype=torch.long)
    for _ in range(max_length):
        logits = options(td)["option_logits"][rows, which]
        action = torch.multinomial(torch.softmax(logits, -1), 1, generator=generator).squeeze(-1)
        td["action"] = action
        td = batched.step(td)
        nxt = td["next"]
        positions.append(torch.where(alive[:, None], nxt["agent_pos"], positions[-1]))
        lengths += alive.long()
        stop = torch.rand(n, generator=generator) < torch.sigmoid(options(nxt.clone())["termination_logits"][rows, which])
        alive &= ~(stop | nxt["done"].reshape(n))
        if not alive.any():
            break
        # keep the target fixed (an apple taken respawns elsewhere): the pictures show one target
        td = nxt.clone()
        td.set("target_pos", torch.as_tensor(target).expand(n, 2).clone())
        td.set("observation", _observe(batched, td["agent_pos"], td["target_pos"]))
    stacked = torch.stack(positions, 1).numpy()
    out: list[list[np.ndarray]] = [[] for _ in range(K)]
    for i in range(n):
        out[int(which[i])].append(stacked[i, : int(lengths[i])])
    return out


def _observe(env: GridWorldEnv, agent: Tensor, target: Tensor) -> Tensor:
    return env._observe(agent.reshape(-1, 2), target.reshape(-1, 2)).reshape(*env.batch_size, -1)


def draw_options(
    options: TensorDictModuleBase,
    env: GridWorldEnv | Mapping[str, Any],
    path: str | os.PathLike,
    *,
    target_pos: Sequence[int] | None = None,
    num_starts: int = 3,
    max_length: int = 30,
    cell_size: int = 20,
    seed: int = 0,
) -> np.ndarray:
    """Writes a PNG: all options' trajectories, then each option's termination probability and trajectories.

    Returns the RGB picture.

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options import OptionsMLP
        >>> path = os.path.join(tempfile.mkdtemp(), "options.png")
        >>> image = draw_options(OptionsMLP(4, 4, 2), {"grid": "two-rooms", "task": "goal"}, path, cell_size=8)
        >>> image.shape, os.path.getsize(path) > 0  # three panels of 10x20 cells, 4-pixel gaps
        ((80, 488, 3), True)
    """
    probe = env if isinstance(env, GridWorldEnv) else _env(env, 1, seed)
    target = _target(probe, target_pos)
    kind = "apple" if probe.task == "apple" else "goal"
    paths = option_trajectories(
        options, probe, num_starts=num_starts, max_length=max_length, target_pos=target, seed=seed
    )
    term = termination_map(options, probe, target)
    colors = option_colors(len(paths))
    all_paths = [p for option_paths in paths for p in option_paths]
    all_colors = [c for c, option_paths in zip(colors, paths) for _ in option_paths]
    panels = [
        render_grid(probe.grid, target_pos=target, target_kind=kind, cell_size=cell_size, trajectories=all_paths,
                    trajectory_colors=all_colors)
    ]  # fmt: skip
    for k, option_paths in enumerate(paths):
        panels.append(
            render_grid(
                probe.grid, target_pos=target, target_kind=kind, cell_size=cell_size, heatmap=term[k],
                trajectories=option_paths, trajectory_colors=[colors[k]] * len(option_paths),
            )
        )  # fmt: skip
    gap = np.full((panels[0].shape[0], 4, 3), 255, dtype=np.uint8)
    image = np.concatenate([x for panel in panels for x in (panel, gap)][:-1], axis=1)
    if not cv2.imwrite(os.fspath(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {os.fspath(path)!r}.")
    return image


@torch.no_grad()
def hierarchy_trajectories(
    hierarchy,
    env: GridWorldEnv | Mapping[str, Any],
    *,
    level: int | None = None,
    num_starts: int = 3,
    max_length: int = 60,
    seed: int = 0,
) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """Trajectories of each option of ``level`` of an :class:`~torchrl_options.OptionHierarchy`, run by the
    nested :class:`~torchrl_options.OptionExecutor` s (call-and-return) from random starts until it terminates.

    Returns, per option, ``num_starts`` pairs ``(positions [T + 1, 2], lower [T])`` where ``lower[t]`` is the
    option of the level below that chose the primitive action at step t (``-1``: the option chose a primitive
    action itself).

    Examples:
        >>> from torchrl_options import OptionHierarchy, OptionsMLP
        >>> h = OptionHierarchy(4, [OptionsMLP(4, 4, 2), OptionsMLP(4, 6, 2)])
        >>> paths = hierarchy_trajectories(h, {"grid": "four-rooms"}, num_starts=2, max_length=5)
        >>> len(paths), len(paths[0]), paths[0][0][0].shape[1]
        (2, 2, 2)
    """
    level = hierarchy.num_levels if level is None else level
    probe = env if isinstance(env, GridWorldEnv) else _env(env, 1, seed)
    K = int(hierarchy.num_options[level - 1])
    n = K * num_starts
    base = _env(probe, n, seed)
    envs = base
    for executor in hierarchy.executors()[:level]:
        envs = envs.append_transform(executor)
    envs.set_seed(seed)
    generator = torch.Generator().manual_seed(seed)
    free = base.grid.free_cells
    starts = free[torch.randint(0, len(free), (n,), generator=generator)]
    which = torch.arange(K).repeat_interleave(num_starts)
    td = envs.reset()
    placed = base.reset_at(agent_pos=starts, target_pos=_target(probe, None))
    td.update(placed.select("agent_pos", "target_pos", "observation"))
    running_key = "option" if level == 1 else f"option_{level}"
    lower_key = None if level == 1 else ("executed_option" if level == 2 else f"executed_option_{level - 1}")
    first = torch.tensor([hierarchy.option_index(level, int(k)) for k in which])
    positions, lowers = [td["agent_pos"].clone()], []
    alive = torch.ones(n, dtype=torch.bool)
    lengths = torch.zeros(n, dtype=torch.long)
    for t in range(max_length):
        td["action"] = first  # used at the first step only: afterwards the option runs and the action is ignored
        td = envs.step(td)
        nxt = td["next"]
        positions.append(torch.where(alive[:, None], nxt["agent_pos"], positions[-1]))
        lower = nxt[lower_key].reshape(n) if lower_key is not None else torch.full((n,), -1)
        lowers.append(lower)
        lengths += alive.long()
        # the option has returned when no option of its level is running any more
        alive &= (nxt[running_key].reshape(n) >= 0) & ~nxt["done"].reshape(n)
        if not alive.any():
            break
        td = nxt.clone()
    stacked = torch.stack(positions, 1).numpy()
    low = torch.stack(lowers, 1).numpy()
    out: list[list[tuple[np.ndarray, np.ndarray]]] = [[] for _ in range(K)]
    for i in range(n):
        L = int(lengths[i])
        out[int(which[i])].append((stacked[i, : L + 1], low[i, :L]))
    return out


def draw_hierarchy(
    hierarchy,
    env: GridWorldEnv | Mapping[str, Any],
    path: str | os.PathLike,
    *,
    num_starts: int = 3,
    max_length: int = 60,
    cell_size: int = 20,
    seed: int = 0,
) -> np.ndarray:
    """Writes a PNG like the paper's figure 1: one panel per option of every level, each drawn by its
    trajectories from random starts; the steps of a level-2 (or higher) option are coloured by the option of the
    level below that was running (grey: a primitive action chosen by the option itself). Returns the picture.

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options import OptionHierarchy, OptionsMLP
        >>> h = OptionHierarchy(4, [OptionsMLP(4, 4, 2), OptionsMLP(4, 6, 2)])
        >>> image = draw_hierarchy(h, {"grid": "four-rooms"}, os.path.join(tempfile.mkdtemp(), "h.png"),
        ...                        num_starts=1, max_length=4, cell_size=4)
        >>> image.shape[0] == 2 * 15 * 4 + 4  # a row of panels per level
        True
    """
    probe = env if isinstance(env, GridWorldEnv) else _env(env, 1, seed)
    kind = "apple" if probe.task == "apple" else "goal"
    target = _target(probe, None)
    grey = (150, 150, 150)
    rows = []
    for level in range(1, hierarchy.num_levels + 1):
        below = option_colors(hierarchy.num_options[level - 2]) if level > 1 else None
        own = option_colors(hierarchy.num_options[level - 1])
        panels = []
        for k, runs in enumerate(hierarchy_trajectories(
            hierarchy, probe, level=level, num_starts=num_starts, max_length=max_length, seed=seed
        )):  # fmt: skip
            image = render_grid(probe.grid, target_pos=target, target_kind=kind, cell_size=cell_size)
            for positions, lower in runs:
                for t in range(len(lower)):
                    color = own[k] if below is None else (grey if lower[t] < 0 else below[int(lower[t])])
                    draw_trajectory(image, positions[t : t + 2], cell_size=cell_size, color=color, mark_ends=False)
            panels.append(image)
        gap = np.full((panels[0].shape[0], 4, 3), 255, dtype=np.uint8)
        rows.append(np.concatenate([x for panel in panels for x in (panel, gap)][:-1], axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0)), constant_values=255) for r in rows]
    hgap = np.full((4, width, 3), 255, dtype=np.uint8)
    image = np.concatenate([x for r in rows for x in (r, hgap)][:-1], axis=0)
    if not cv2.imwrite(os.fspath(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {os.fspath(path)!r}.")
    return image
