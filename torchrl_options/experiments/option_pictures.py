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

from torchrl_options.envs import GridWorldEnv, option_colors, render_grid

__all__ = ["termination_map", "option_trajectories", "draw_options"]


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
