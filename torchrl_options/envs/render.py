"""Pictures of GridWorlds with OpenCV: the grid, the agent and its target, trajectories and per-cell heat maps.

These draw the paper's option pictures: trajectories of each option from random initial states (figure 1) and
termination probabilities over the grid (figure 6). All functions work on RGB ``uint8`` arrays of shape
``[H * cell_size, W * cell_size, 3]``; positions are ``(row, col)``.
"""
from __future__ import annotations

import colorsys
import logging
import math
from pathlib import Path
from typing import Sequence

import cv2
import numpy as np
import torch
from torch import Tensor

from torchrl_options.checks import check_int, check_number
from torchrl_options.envs.maps import GridMap

__all__ = [
    "draw_heatmap",
    "draw_trajectory",
    "option_colors",
    "render_grid",
    "write_video",
]

logger = logging.getLogger(__name__)

Color = tuple[int, int, int]
WALL_COLOR: Color = (48, 48, 56)
FREE_COLOR: Color = (245, 245, 240)
LINE_COLOR: Color = (215, 215, 210)
AGENT_COLOR: Color = (40, 90, 220)
APPLE_COLOR: Color = (220, 40, 40)
GOAL_COLOR: Color = (30, 170, 60)
HEAT_COLOR: Color = (220, 30, 30)


def _walls(grid: GridMap | Tensor | np.ndarray) -> np.ndarray:
    walls = grid.walls if isinstance(grid, GridMap) else grid
    if isinstance(walls, Tensor):
        walls = walls.detach().cpu().numpy()
    return np.asarray(walls, dtype=bool)


def _numpy(x: Tensor | np.ndarray | Sequence) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _centre(pos: Sequence[float], cell_size: int, offset: float = 0.0) -> tuple[int, int]:
    """Pixel ``(x, y)`` of the centre of cell ``(row, col)`` (shifted by ``offset`` cells)."""
    row, col = float(pos[0]), float(pos[1])
    return (int(round((col + 0.5 + offset) * cell_size)), int(round((row + 0.5 + offset) * cell_size)))


def option_colors(k: int) -> list[Color]:
    """``k`` well separated RGB colours (one per option).

    Examples:
        >>> option_colors(2)
        [(230, 25, 25), (25, 230, 230)]
    """
    check_int(k, "k", minimum=0)
    return [
        tuple(int(round(255 * v)) for v in colorsys.hsv_to_rgb(i / max(k, 1), 0.89, 0.9)) for i in range(k)
    ]


def draw_heatmap(
    image: np.ndarray,
    grid: GridMap | Tensor | np.ndarray,
    values: Tensor | np.ndarray,
    *,
    cell_size: int,
    color: Color = HEAT_COLOR,
    vmin: float | None = 0.0,
    vmax: float | None = 1.0,
) -> np.ndarray:
    """Tints each free cell from white (``vmin``) to ``color`` (``vmax``), in place.

    Args:
        image: the picture (from :func:`render_grid`).
        grid: the map (or its ``[H, W]`` walls).
        values: ``[H, W]`` per-cell values, or ``[F]`` per free cell (row-major order, like
            :attr:`GridMap.free_cells`). NaN cells are left untouched.
        cell_size: pixels per cell.
        color: the colour of ``vmax``.
        vmin, vmax: the value range; ``None`` takes the min / max of the values.

    Returns:
        ``image``.

    Examples:
        >>> from torchrl_options.envs.maps import load_map
        >>> grid = load_map("two-rooms")
        >>> image = render_grid(grid, cell_size=8)
        >>> image = draw_heatmap(image, grid, torch.rand(grid.num_free), cell_size=8)
        >>> image.shape
        (80, 160, 3)
    """
    walls = _walls(grid)
    values = _numpy(values).astype(np.float64)
    if values.shape == (int((~walls).sum()),):
        full = np.full(walls.shape, np.nan)
        full[~walls] = values
        values = full
    if values.shape != walls.shape:
        raise ValueError(f"values must be [H, W] = {walls.shape} or [F], got {values.shape}.")
    check_int(cell_size, "cell_size", minimum=1)
    finite = np.isfinite(values) & ~walls
    if not finite.any():
        return image
    lo = float(values[finite].min()) if vmin is None else vmin
    hi = float(values[finite].max()) if vmax is None else vmax
    scale = np.clip((values - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    white, target = np.array(FREE_COLOR, dtype=np.float64), np.array(color, dtype=np.float64)
    for r, c in zip(*np.nonzero(finite)):
        tint = tuple(int(v) for v in np.round(white + scale[r, c] * (target - white)))
        cv2.rectangle(
            image, (c * cell_size + 1, r * cell_size + 1), ((c + 1) * cell_size - 1, (r + 1) * cell_size - 1), tint, -1
        )
    return image


def draw_trajectory(
    image: np.ndarray,
    positions: Tensor | np.ndarray | Sequence[Sequence[int]],
    *,
    cell_size: int,
    color: Color = AGENT_COLOR,
    thickness: int | None = None,
    offset: float = 0.0,
    mark_ends: bool = True,
) -> np.ndarray:
    """Draws a polyline through the cell centres of ``positions`` (``[T, 2]`` rows and cols), in place.

    Args:
        image: the picture.
        positions: the visited cells, in order.
        cell_size: pixels per cell.
        color: line colour.
        thickness: line width in pixels (defaults to ``cell_size // 8``, at least 1).
        offset: a shift in cells (e.g. ``+-0.15``) to tell apart trajectories sharing cells.
        mark_ends: a dot at the first cell, a square at the last.

    Returns:
        ``image``.

    Examples:
        >>> image = render_grid(torch.zeros(3, 3, dtype=torch.bool), cell_size=10)
        >>> image = draw_trajectory(image, [(0, 0), (0, 1), (1, 1)], cell_size=10, color=(255, 0, 0))
        >>> int(image[5, 10].argmax())  # red, on the segment (0, 0) -> (0, 1)
        0
    """
    raw = _numpy(positions)
    if raw.ndim != 2 or raw.shape[-1] != 2:
        raise ValueError(f"positions must be [T, 2] (row, col) cells, got shape {list(raw.shape)}.")
    check_int(cell_size, "cell_size", minimum=1)
    points = raw.reshape(-1, 2)
    if len(points) == 0:
        return image
    thickness = max(cell_size // 8, 1) if thickness is None else thickness
    pixels = np.array([_centre(p, cell_size, offset) for p in points], dtype=np.int32)
    if len(pixels) > 1:
        cv2.polylines(image, [pixels.reshape(-1, 1, 2)], False, color, thickness, cv2.LINE_AA)
    if mark_ends:
        radius = max(cell_size // 6, 2)
        cv2.circle(image, tuple(int(v) for v in pixels[0]), radius, color, -1, cv2.LINE_AA)
        x, y = (int(v) for v in pixels[-1])
        cv2.rectangle(image, (x - radius, y - radius), (x + radius, y + radius), color, -1)
    return image


def render_grid(
    grid: GridMap | Tensor | np.ndarray,
    agent_pos: Tensor | Sequence[int] | None = None,
    target_pos: Tensor | Sequence[int] | None = None,
    *,
    cell_size: int = 24,
    target_kind: str = "apple",
    heatmap: Tensor | np.ndarray | None = None,
    heatmap_color: Color = HEAT_COLOR,
    heatmap_range: tuple[float | None, float | None] = (0.0, 1.0),
    trajectories: Sequence[Tensor | np.ndarray] | None = None,
    trajectory_colors: Sequence[Color] | None = None,
    grid_lines: bool = True,
) -> np.ndarray:
    """Draws a GridWorld as an RGB ``uint8`` array ``[H * cell_size, W * cell_size, 3]``.

    Layers, bottom to top: cells (walls dark), an optional per-cell heat map, grid lines, trajectories, the
    target (a red disc for an apple, a green square for a goal) and the agent (a blue disc).

    Args:
        grid: the map, or its ``[H, W]`` walls (bool).
        agent_pos, target_pos: ``(row, col)``, optional.
        cell_size: pixels per cell.
        target_kind: ``"apple"`` or ``"goal"``.
        heatmap: per-cell values (see :func:`draw_heatmap`), e.g. an option's termination probability.
        heatmap_color, heatmap_range: colour of the top of the range, and ``(vmin, vmax)``.
        trajectories: ``[T, 2]`` position sequences drawn as polylines.
        trajectory_colors: one colour per trajectory (defaults to :func:`option_colors`).
        grid_lines: thin lines between free cells.

    Examples:
        >>> from torchrl_options.envs.maps import load_map
        >>> image = render_grid(load_map("four-rooms"), agent_pos=(1, 1), target_pos=(13, 9), cell_size=16)
        >>> image.shape, image.dtype
        ((240, 176, 3), dtype('uint8'))
        >>> image[0, 0].tolist(), image[1 * 16 + 8, 1 * 16 + 8].tolist()  # a wall, the agent
        ([48, 48, 56], [40, 90, 220])
    """
    check_int(cell_size, "cell_size", minimum=1)
    walls = _walls(grid)
    H, W = walls.shape
    image = np.empty((H * cell_size, W * cell_size, 3), dtype=np.uint8)
    image[:] = FREE_COLOR
    cells = np.kron(walls, np.ones((cell_size, cell_size), dtype=bool))
    image[cells] = WALL_COLOR
    if heatmap is not None:
        draw_heatmap(
            image, walls, heatmap, cell_size=cell_size, color=heatmap_color, vmin=heatmap_range[0],
            vmax=heatmap_range[1],
        )  # fmt: skip
    if grid_lines and cell_size >= 6:
        for r in range(1, H):
            cv2.line(image, (0, r * cell_size), (W * cell_size - 1, r * cell_size), LINE_COLOR, 1)
        for c in range(1, W):
            cv2.line(image, (c * cell_size, 0), (c * cell_size, H * cell_size - 1), LINE_COLOR, 1)
        image[cells] = WALL_COLOR
    if trajectories is not None:
        colors = list(trajectory_colors) if trajectory_colors is not None else option_colors(len(trajectories))
        for path, color in zip(trajectories, colors):
            draw_trajectory(image, path, cell_size=cell_size, color=color)
    radius = max(int(cell_size * 0.35), 1)
    if target_pos is not None:
        target = _numpy(target_pos).reshape(2)
        x, y = _centre(target, cell_size)
        if target_kind == "apple":
            cv2.circle(image, (x, y), radius, APPLE_COLOR, -1, cv2.LINE_AA)
        elif target_kind == "goal":
            cv2.rectangle(image, (x - radius, y - radius), (x + radius, y + radius), GOAL_COLOR, -1)
        else:
            raise ValueError(f"target_kind must be 'apple' or 'goal', got {target_kind!r}.")
    if agent_pos is not None:
        cv2.circle(image, _centre(_numpy(agent_pos).reshape(2), cell_size), radius, AGENT_COLOR, -1, cv2.LINE_AA)
    return image


def write_video(frames: Sequence[np.ndarray], path: str | Path, fps: float = 8.0) -> Path:
    """Writes RGB frames (all the same shape) to a video file with OpenCV (``.mp4``: codec ``mp4v``; ``.avi``:
    ``MJPG``). Returns the path.

    Examples:
        >>> import tempfile, os
        >>> frames = [render_grid(torch.zeros(4, 4, dtype=torch.bool), agent_pos=(i, i), cell_size=8) for i in range(4)]
        >>> path = write_video(frames, os.path.join(tempfile.mkdtemp(), "walk.avi"))
        >>> path.stat().st_size > 0
        True
    """
    path = Path(path)
    if not frames:
        raise ValueError("write_video needs at least one frame.")
    check_number(fps, "fps", lo=0.0, hi=math.inf, lo_open=True, hi_open=True)
    if not path.parent.is_dir():
        raise ValueError(f"{path}: cannot write the video: the folder {path.parent} does not exist.")
    height, width = frames[0].shape[:2]
    fourcc = cv2.VideoWriter_fourcc(*("MJPG" if path.suffix.lower() == ".avi" else "mp4v"))
    writer = cv2.VideoWriter(str(path), fourcc, fps, (width, height))
    if not writer.isOpened():
        raise RuntimeError(f"OpenCV could not open a video writer for {path}.")
    try:
        for frame in frames:
            if frame.shape[:2] != (height, width):
                raise ValueError("All frames must have the same shape.")
            writer.write(cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2BGR))
    finally:
        writer.release()
    return path
