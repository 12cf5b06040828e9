"""Pictures of discovered options, like figures 1 and 6 of Fox et al. (2017), "Multi-Level Discovery of Deep Options".

Figure 1 draws each option's trajectories from random initial states until it terminates, one colour per option;
figure 6 draws an option's termination probability over the grid in red. :func:`draw_options` puts both in one
PNG: a first panel with every option's trajectories, then one panel per option with its termination probability
``sigmoid(termination_logits)`` at every free cell (for a fixed target) under its own trajectories; titles, axes
(the map's columns and rows), a legend, a colour bar and a caption say what the panels show.
:func:`option_video` plays the same trajectories as a captioned video (OpenCV), and :func:`draw_hierarchy`
draws the options of every level of a hierarchy. The figures need matplotlib (the ``recipes`` extra).
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
from torchrl_options.envs.render import APPLE_COLOR, FREE_COLOR, GOAL_COLOR, HEAT_COLOR

__all__ = [
    "termination_map", "option_trajectories", "draw_options", "option_video", "hierarchy_trajectories", "draw_hierarchy"
]


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


def _figure(num_rows: int, num_cols: int, grid_shape: tuple[int, int], caption: str, extra_width: float = 0.0):
    """A captioned ``Figure`` of ``num_rows x num_cols`` map panels: ``(figure, panels' subfigure, axes)``."""
    from torchrl_options.experiments.plotting import _captioned_figure

    H, W = grid_shape
    return _captioned_figure(num_rows, num_cols, (2.6, 2.6 * H / W + 0.6), caption, extra_width + 0.6)


def _show_map(ax, panel: np.ndarray, grid_shape: tuple[int, int], title: str) -> None:
    """The rendered map in cell coordinates (x: column, y: row), titled."""
    H, W = grid_shape
    ax.imshow(panel, extent=(-0.5, W - 0.5, H - 0.5, -0.5), interpolation="nearest")
    ax.set_title(title, fontsize=9)
    ax.set_xlabel("column", fontsize=8)
    ax.set_ylabel("row", fontsize=8)
    ax.tick_params(labelsize=7)


def _rgb(color: Sequence[int]) -> tuple[float, ...]:
    return tuple(v / 255 for v in color)


def _target_handle(kind: str):
    from matplotlib.lines import Line2D

    if kind == "apple":
        return Line2D([], [], marker="o", linestyle="", color=_rgb(APPLE_COLOR), label="apple (the fixed target)")
    return Line2D([], [], marker="s", linestyle="", color=_rgb(GOAL_COLOR), label="goal (the fixed target)")


def _save(fig, path: str | os.PathLike) -> None:
    try:
        fig.savefig(os.fspath(path), dpi=110)
    except OSError as e:
        raise OSError(f"could not write {os.fspath(path)!r}: {e}") from e


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
    title: str | None = None,
):
    """Writes a PNG like figures 1 and 6 of the paper, titled, with axes, legend, colour bar and a caption.

    The first panel draws every option's trajectories (:func:`option_trajectories`: ``num_starts`` random
    starts per option, the target fixed, until the option terminates), one colour per option; then one panel per
    option draws its trajectories over its termination probability at each free cell
    (:func:`termination_map`, white 0 to red 1, the colour bar). Axes are the map's columns and rows; a caption
    under the panels says what they show. Needs matplotlib (the ``recipes`` extra).

    Args:
        options: the options (``option_logits``, ``termination_logits`` and ``num_options``).
        env: the GridWorld (or its arguments).
        path: the PNG to write.

    Keyword Args:
        target_pos: the target's cell, fixed in every picture; default the env's first subgoal or goal.
        num_starts, max_length, seed: the trajectories (:func:`option_trajectories`).
        cell_size (int): pixels per cell of the rendered map.
        title (str, optional): the figure's title (e.g. the run and the option file).

    Returns:
        The matplotlib ``Figure`` (written, not shown; it holds no pyplot state).

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options import OptionsMLP
        >>> path = os.path.join(tempfile.mkdtemp(), "options.png")
        >>> fig = draw_options(OptionsMLP(4, 4, 2), {"grid": "two-rooms", "task": "goal"}, path, cell_size=8)
        >>> [ax.get_title() for ax in fig.axes[:3]]
        ['every option, 3 starts each', 'option 0: termination', 'option 1: termination']
        >>> os.path.getsize(path) > 0
        True
    """
    from matplotlib import cm, colors
    from matplotlib.lines import Line2D

    probe = env if isinstance(env, GridWorldEnv) else _env(env, 1, seed)
    target = _target(probe, target_pos)
    kind = "apple" if probe.task == "apple" else "goal"
    paths = option_trajectories(
        options, probe, num_starts=num_starts, max_length=max_length, target_pos=target, seed=seed
    )
    term = termination_map(options, probe, target)
    K = len(paths)
    option_rgb = option_colors(K)
    all_paths = [p for option_paths in paths for p in option_paths]
    all_colors = [c for c, option_paths in zip(option_rgb, paths) for _ in option_paths]
    grid_shape = tuple(probe.grid.walls.shape)
    caption = (
        f"Left panel: the trajectories of all {K} options, one colour per option, each run from {num_starts} "
        f"uniformly random start cells (seed {seed}) with the {kind} fixed at cell {tuple(target)} (row, column) "
        f"until the option terminates (its termination drawn at every step), the episode ends or {max_length} steps "
        "pass; a dot marks a start, a square the cell where the option stopped. Next panels, one per option: that "
        "option's trajectories over its termination probability sigmoid(termination_logits) with the agent at "
        "each free cell (white: 0, red: 1; see the colour bar). Dark cells are walls."
    )
    fig, main, axes = _figure(1, K + 1, grid_shape, caption, extra_width=1.0)
    if title:
        main.suptitle(title, fontsize=10)
    panel = render_grid(probe.grid, target_pos=target, target_kind=kind, cell_size=cell_size, trajectories=all_paths,
                        trajectory_colors=all_colors)  # fmt: skip
    _show_map(axes[0, 0], panel, grid_shape, f"every option, {num_starts} starts each")
    for k, option_paths in enumerate(paths):
        panel = render_grid(
            probe.grid, target_pos=target, target_kind=kind, cell_size=cell_size, heatmap=term[k],
            trajectories=option_paths, trajectory_colors=[option_rgb[k]] * len(option_paths),
        )  # fmt: skip
        _show_map(axes[0, k + 1], panel, grid_shape, f"option {k}: termination")
    heat = colors.LinearSegmentedColormap.from_list("termination", [_rgb(FREE_COLOR), _rgb(HEAT_COLOR)])
    bar = main.colorbar(cm.ScalarMappable(colors.Normalize(0.0, 1.0), heat), ax=list(axes[0, 1:]), shrink=0.8)
    bar.set_label("termination probability", fontsize=8)
    handles = [Line2D([], [], color=_rgb(c), linewidth=2, label=f"option {k}") for k, c in enumerate(option_rgb)]
    handles += [
        Line2D([], [], marker="o", linestyle="", color="dimgray", label="start"),
        Line2D([], [], marker="s", linestyle="", color="dimgray", label="end (terminated)"),
        _target_handle(kind),
    ]
    main.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 7), fontsize=8)
    _save(fig, path)
    return fig


def _caption_band(lines: Sequence[str], width: int) -> np.ndarray:
    """A white band with ``lines`` of black text, to put above a video frame."""
    line_h = 15
    band = np.full((line_h * len(lines) + 6, width, 3), 255, dtype=np.uint8)
    for i, text in enumerate(lines):
        cv2.putText(band, text, (4, line_h * (i + 1)), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 1, cv2.LINE_AA)
    return band


def option_video(
    options: TensorDictModuleBase,
    env: GridWorldEnv | Mapping[str, Any],
    path: str | os.PathLike,
    *,
    target_pos: Sequence[int] | None = None,
    num_starts: int = 3,
    max_length: int = 30,
    cell_size: int = 20,
    fps: float = 4.0,
    seed: int = 0,
) -> int:
    """Writes a video (OpenCV: ``.avi`` MJPG or ``.mp4`` mp4v) of each option run from a few start states.

    The trajectories are those of :func:`option_trajectories` (same arguments, same seed: the same paths as
    :func:`draw_options`). Options play one after the other, each from its ``num_starts`` starts, one frame per
    visited cell: the agent (blue disc) on the option's path so far, over the option's termination probability
    at each free cell (white 0 to red 1), under a caption naming the option, the start, the step and the
    probability that the option terminates where the agent stands. Like the Atari ``option_frames``.

    Returns:
        The number of frames: the sum over trajectories of their number of visited cells.

    Examples:
        >>> import os, tempfile, cv2
        >>> from torchrl_options import OptionsMLP
        >>> path = os.path.join(tempfile.mkdtemp(), "options.avi")
        >>> n = option_video(OptionsMLP(4, 4, 2), {"grid": "four-rooms"}, path, num_starts=2, max_length=5)
        >>> int(cv2.VideoCapture(path).get(cv2.CAP_PROP_FRAME_COUNT)) == n
        True
    """
    from torchrl_options.envs.render import write_video

    if num_starts < 1 or max_length < 0:
        raise ValueError(f"option_video needs num_starts >= 1 and max_length >= 0, got {num_starts} and {max_length}.")
    probe = env if isinstance(env, GridWorldEnv) else _env(env, 1, seed)
    target = _target(probe, target_pos)
    kind = "apple" if probe.task == "apple" else "goal"
    paths = option_trajectories(
        options, probe, num_starts=num_starts, max_length=max_length, target_pos=target, seed=seed
    )
    term = termination_map(options, probe, target)
    index = {tuple(int(v) for v in cell): i for i, cell in enumerate(probe.grid.free_cells.tolist())}
    K = len(paths)
    colors = option_colors(K)
    frames = []
    for k, option_paths in enumerate(paths):
        for s, cells in enumerate(option_paths):
            for t in range(len(cells)):
                image = render_grid(
                    probe.grid, agent_pos=cells[t], target_pos=target, target_kind=kind, cell_size=cell_size,
                    heatmap=term[k], trajectories=[cells[: t + 1]], trajectory_colors=[colors[k]],
                )  # fmt: skip
                stop = float(term[k, index[tuple(int(v) for v in cells[t])]])
                last = t == len(cells) - 1
                status = ("option stopped" if len(cells) <= max_length else "step limit") if last else "running"
                lines = [
                    f"option {k} of {K}, start {s + 1} of {num_starts}",
                    f"step {t}: {status}",
                    f"P(terminate here) = {stop:.2f}",
                    "red cells: P(terminate)",
                ]
                frames.append(np.concatenate([_caption_band(lines, image.shape[1]), image], axis=0))
    write_video(frames, path, fps=fps)
    return len(frames)


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
    title: str | None = None,
):
    """Writes a PNG like the paper's figure 1: one row of panels per level, one panel per option, each drawn by
    its trajectories from random starts (:func:`hierarchy_trajectories`); the steps of a level-2 (or higher)
    option are coloured by the option of the level below that was running (grey: a primitive action chosen by
    the option itself). A legend names the colours; a caption under the panels says what they show. Needs
    matplotlib (the ``recipes`` extra). Returns the matplotlib ``Figure`` (written, not shown).

    Examples:
        >>> import os, tempfile
        >>> from torchrl_options import OptionHierarchy, OptionsMLP
        >>> h = OptionHierarchy(4, [OptionsMLP(4, 4, 2), OptionsMLP(4, 6, 2)])
        >>> fig = draw_hierarchy(h, {"grid": "four-rooms"}, os.path.join(tempfile.mkdtemp(), "h.png"),
        ...                      num_starts=1, max_length=4, cell_size=4)
        >>> [ax.get_title() for ax in fig.axes]  # a row of panels per level
        ['level 1, option 0', 'level 1, option 1', 'level 2, option 0', 'level 2, option 1']
    """
    from matplotlib.lines import Line2D

    probe = env if isinstance(env, GridWorldEnv) else _env(env, 1, seed)
    kind = "apple" if probe.task == "apple" else "goal"
    target = _target(probe, None)
    grey = (150, 150, 150)
    grid_shape = tuple(probe.grid.walls.shape)
    levels = hierarchy.num_levels
    caption = (
        f"Each panel runs one option of a {levels}-level hierarchy with the nested call-and-return executors from "
        f"{num_starts} uniformly random start cells (seed {seed}) until it returns, the episode ends or "
        f"{max_length} steps pass. Level 1: the trajectories in the option's own colour. Level 2 and above: each "
        "step is coloured by the option of the level below that chose its primitive action (grey: a primitive "
        f"action chosen by the option itself). Dark cells are walls; the {kind} is at cell {tuple(target)} "
        "(row, column)."
    )
    fig, main, axes = _figure(levels, max(hierarchy.num_options), grid_shape, caption, extra_width=0.2)
    if title:
        main.suptitle(title, fontsize=10)
    for level in range(1, levels + 1):
        below = option_colors(hierarchy.num_options[level - 2]) if level > 1 else None
        own = option_colors(hierarchy.num_options[level - 1])
        row = axes[level - 1]
        runs_per_option = hierarchy_trajectories(
            hierarchy, probe, level=level, num_starts=num_starts, max_length=max_length, seed=seed
        )
        for k, runs in enumerate(runs_per_option):
            image = render_grid(probe.grid, target_pos=target, target_kind=kind, cell_size=cell_size)
            for positions, lower in runs:
                for t in range(len(lower)):
                    color = own[k] if below is None else (grey if lower[t] < 0 else below[int(lower[t])])
                    draw_trajectory(image, positions[t : t + 2], cell_size=cell_size, color=color, mark_ends=False)
            _show_map(row[k], image, grid_shape, f"level {level}, option {k}")
        for ax in row[len(runs_per_option) :]:
            ax.remove()
    handles = []
    for level in range(1, max(levels - 1, 1) + 1):  # the colours of level L: its own panels (L = 1), level L + 1's
        handles += [
            Line2D([], [], color=_rgb(c), linewidth=2, label=f"level-{level} option {j}")
            for j, c in enumerate(option_colors(hierarchy.num_options[level - 1]))
        ]
    if levels > 1:
        handles.append(Line2D([], [], color=_rgb(grey), linewidth=2, label="primitive action"))
    handles.append(_target_handle(kind))
    main.legend(handles=handles, loc="outside lower center", ncol=min(len(handles), 6), fontsize=8)
    _save(fig, path)
    return fig
