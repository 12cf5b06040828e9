"""GridWorld maps: parsing, the built-in maps of the DDO paper, and room detection.

A map file holds one row per line and one integer per cell, separated by spaces (the format of the DDO authors'
GridWorld maps):

====  =====================================================================================
code  meaning
====  =====================================================================================
0     free cell
1     wall
2     start cell (at most one)
3     goal cell; in the ``"subgoals"`` task, the first sub-goal
4     second sub-goal of the ``"subgoals"`` task (an extension of the authors' legend)
====  =====================================================================================

Cells marked 2, 3 or 4 are free cells. The apple task ignores the markers.

Built-in maps (package data, read with :mod:`importlib.resources`):

- ``"four-rooms"``: the 15x11 four-rooms map of the paper (section 5.1); the DDO authors' own file. Four 3x3
  rooms in the corners joined by an H of one-cell corridors.
- ``"two-rooms"``: 10x20, two 8x5 rooms joined by an 8-cell corridor; drawn for this package from the paper's
  appendix B ("a 10x20 GridWorld environment with two rooms"), in the spirit of the authors' 8x20 map.
- ``"two-rooms-8x20"``: the authors' 8x20 two-rooms map (two 6x3 rooms, a 12-cell corridor).
- ``"three-rooms"``: 10x25, three rooms left to right joined by two 2-cell corridors (at different rows); drawn
  for this package from appendix B. The start (2) is in the leftmost room, the first sub-goal (3) in the middle
  room and the second sub-goal (4) in the rightmost room.

Rows and columns are indexed from the top-left corner: a position is ``(row, col)``.
"""
from __future__ import annotations

import logging
from collections import deque
from dataclasses import dataclass, field
from functools import cached_property
from importlib import resources
from pathlib import Path
from typing import Sequence

import torch
from torch import Tensor

__all__ = [
    "ACTION_NAMES",
    "MOVES",
    "GridMap",
    "available_maps",
    "detect_rooms",
    "load_map",
    "parse_map",
]

logger = logging.getLogger(__name__)

#: The four moves, indexed by action: up, right, down, left (clockwise from the top), as ``(d_row, d_col)``.
MOVES = torch.tensor([[-1, 0], [0, 1], [1, 0], [0, -1]], dtype=torch.long)
ACTION_NAMES = ("up", "right", "down", "left")

FREE, WALL, START, GOAL, GOAL2 = 0, 1, 2, 3, 4

_BUILTIN = {
    "four-rooms": "four-rooms-15x11.txt",
    "two-rooms": "two-rooms-10x20.txt",
    "two-rooms-10x20": "two-rooms-10x20.txt",
    "two-rooms-8x20": "two-rooms-8x20.txt",
    "three-rooms": "three-rooms-10x25.txt",
    "three-rooms-10x25": "three-rooms-10x25.txt",
}


@dataclass(eq=False)
class GridMap:
    """A GridWorld map: walls, start/goal markers and rooms.

    Derived tables (free cells, cell indices, the transition table, rooms) are computed once and cached. They live
    on the CPU; :class:`~torchrl_options.envs.GridWorldEnv` copies what it needs to its device.

    Args:
        walls (Tensor): ``[H, W]`` bool, ``True`` on walls.
        start (tuple[int, int], optional): the start marker ``(row, col)``.
        goals (tuple of (int, int)): the goal markers, in order (code 3 then code 4).
        rooms (Tensor, optional): ``[H, W]`` long room labelling, ``-1`` outside rooms (corridors, walls) and
            ``0..R-1`` inside. Defaults to :func:`detect_rooms` ``(walls)``.
        name (str): a name for messages and pictures.

    Examples:
        >>> grid = load_map("four-rooms")
        >>> grid.shape, grid.num_free, grid.num_rooms
        ((15, 11), 53, 4)
        >>> grid.start, grid.goals
        ((1, 1), ((3, 3),))
        >>> [len(c) for c in grid.room_cells]
        [9, 9, 9, 9]
    """

    walls: Tensor
    start: tuple[int, int] | None = None
    goals: tuple[tuple[int, int], ...] = ()
    rooms: Tensor | None = None
    name: str = "custom"
    _room_ids: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        walls = torch.as_tensor(self.walls)
        if walls.ndim != 2 or walls.numel() == 0:
            raise ValueError(f"walls must be a non-empty [H, W] tensor, got shape {tuple(walls.shape)}.")
        self.walls = walls.to(torch.bool).cpu()
        for pos in ([self.start] if self.start is not None else []) + list(self.goals):
            if self.is_wall(pos):
                raise ValueError(f"Marker {pos} of map {self.name!r} is a wall or outside the grid.")
        if self.num_free == 0:
            raise ValueError(f"Map {self.name!r} has no free cell.")
        rooms = detect_rooms(self.walls) if self.rooms is None else torch.as_tensor(self.rooms, dtype=torch.long)
        if rooms.shape != self.walls.shape:
            raise ValueError(f"rooms must have the map's shape {self.shape}, got {tuple(rooms.shape)}.")
        if (rooms[self.walls] >= 0).any():
            raise ValueError("rooms labels a wall cell: walls must be -1.")
        labels = rooms[rooms >= 0].unique()
        if labels.numel() and not torch.equal(labels, torch.arange(labels.numel())):
            raise ValueError(f"room labels must be 0..R-1, got {labels.tolist()}.")
        self.rooms = rooms.cpu()

    # ----------------------------------------------------------------------------------------------- geometry
    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``: rows and columns."""
        return tuple(self.walls.shape)

    def is_wall(self, pos: Sequence[int]) -> bool:
        """Whether ``pos = (row, col)`` is a wall or outside the grid."""
        r, c = int(pos[0]), int(pos[1])
        H, W = self.shape
        return not (0 <= r < H and 0 <= c < W) or bool(self.walls[r, c])

    @cached_property
    def free_cells(self) -> Tensor:
        """``[F, 2]`` long: the free cells ``(row, col)`` in row-major order. A cell's index in this table is its
        *cell index*."""
        return (~self.walls).nonzero()

    @property
    def num_free(self) -> int:
        """``F``, the number of free cells."""
        return int((~self.walls).sum())

    @cached_property
    def cell_index(self) -> Tensor:
        """``[H, W]`` long: the cell index of each free cell, ``-1`` on walls."""
        index = torch.full(self.shape, -1, dtype=torch.long)
        index[~self.walls] = torch.arange(self.num_free)
        return index

    @cached_property
    def next_cell(self) -> Tensor:
        """``[F, 4]`` long: the cell index reached from each free cell by each move (itself when a wall, or the
        border of the grid, blocks the move)."""
        H, W = self.shape
        target = self.free_cells[:, None, :] + MOVES[None]
        inside = (target[..., 0] >= 0) & (target[..., 0] < H) & (target[..., 1] >= 0) & (target[..., 1] < W)
        target = torch.where(inside[..., None], target, self.free_cells[:, None, :])
        nxt = self.cell_index[target[..., 0], target[..., 1]]
        return torch.where(nxt >= 0, nxt, torch.arange(self.num_free)[:, None])

    # -------------------------------------------------------------------------------------------------- rooms
    @property
    def num_rooms(self) -> int:
        """``R``, the number of rooms."""
        return int(self.rooms.max()) + 1 if (self.rooms >= 0).any() else 0

    @cached_property
    def room_cells(self) -> list[Tensor]:
        """The cell indices of each room, a list of ``R`` long tensors (row-major order within a room)."""
        room_of_cell = self.cell_room
        return [(room_of_cell == r).nonzero().squeeze(-1) for r in range(self.num_rooms)]

    @cached_property
    def cell_room(self) -> Tensor:
        """``[F]`` long: the room of each free cell, ``-1`` for corridor cells."""
        return self.rooms[~self.walls]

    def room_of(self, pos: Sequence[int]) -> int:
        """The room of ``pos = (row, col)``, ``-1`` outside rooms."""
        return int(self.rooms[int(pos[0]), int(pos[1])])

    def __repr__(self) -> str:
        H, W = self.shape
        return (
            f"GridMap(name={self.name!r}, shape=({H}, {W}), free={self.num_free}, rooms={self.num_rooms}, "
            f"start={self.start}, goals={self.goals})"
        )


def detect_rooms(walls: Tensor) -> Tensor:
    """Labels the rooms of a map: connected free areas at least two cells wide.

    A free cell is a *room cell* when it belongs to some 2x2 block of free cells; rooms are the 4-connected
    components of room cells. One-cell-wide corridors, their junctions and doorways are not room cells, so the
    rule finds the 3x3 corner rooms of the four-rooms map and the rooms of the two- and three-rooms maps. It
    cannot separate rooms joined by an opening two or more cells wide: pass an explicit ``rooms`` labelling to
    :class:`GridMap` for such maps.

    Rooms are numbered by their first cell in column-major order (leftmost room first, top before bottom).

    Args:
        walls (Tensor): ``[H, W]`` bool, ``True`` on walls.

    Returns:
        ``[H, W]`` long tensor, ``-1`` outside rooms, ``0..R-1`` inside.

    Examples:
        >>> grid = parse_map("1 1 1 1 1 1\\n1 0 0 1 0 1\\n1 0 0 0 0 1\\n1 1 1 1 1 1")
        >>> detect_rooms(grid.walls)
        tensor([[-1, -1, -1, -1, -1, -1],
                [-1,  0,  0, -1, -1, -1],
                [-1,  0,  0, -1, -1, -1],
                [-1, -1, -1, -1, -1, -1]])
    """
    free = ~torch.as_tensor(walls, dtype=torch.bool).cpu()
    if free.ndim != 2:
        raise ValueError(f"walls must be an [H, W] grid, got shape {list(free.shape)}.")
    H, W = free.shape
    block = free[:-1, :-1] & free[1:, :-1] & free[:-1, 1:] & free[1:, 1:]  # [H-1, W-1]: block at its top-left
    room_cell = torch.zeros(H, W, dtype=torch.bool)
    for dr in (0, 1):
        for dc in (0, 1):
            room_cell[dr : H - 1 + dr, dc : W - 1 + dc] |= block
    labels = torch.full((H, W), -1, dtype=torch.long)
    is_room = room_cell.tolist()
    next_label = 0
    for c in range(W):  # column-major scan: rooms numbered left to right
        for r in range(H):
            if not is_room[r][c] or labels[r, c] >= 0:
                continue
            labels[r, c] = next_label
            queue = deque([(r, c)])
            while queue:
                i, j = queue.popleft()
                for di, dj in ((-1, 0), (0, 1), (1, 0), (0, -1)):
                    a, b = i + di, j + dj
                    if 0 <= a < H and 0 <= b < W and is_room[a][b] and labels[a, b] < 0:
                        labels[a, b] = next_label
                        queue.append((a, b))
            next_label += 1
    return labels


def parse_map(text: str, name: str = "custom", rooms: Tensor | None = None) -> GridMap:
    """Parses a map from its text (see the module docstring for the format).

    Args:
        text (str): one row per line, integers separated by whitespace. Blank lines are ignored.
        name (str): the map's name.
        rooms (Tensor, optional): an explicit ``[H, W]`` room labelling (see :class:`GridMap`).

    Examples:
        >>> grid = parse_map('''
        ... 1 1 1 1 1
        ... 1 2 0 3 1
        ... 1 1 1 1 1
        ... ''')
        >>> grid.shape, grid.start, grid.goals, grid.num_free
        ((3, 5), (1, 1), ((1, 3),), 3)
    """
    rows = [line.split() for line in text.strip().splitlines() if line.strip()]
    if not rows:
        raise ValueError(f"Map {name!r} is empty.")
    width = len(rows[0])
    if any(len(row) != width for row in rows):
        raise ValueError(f"Map {name!r}: all rows must have the same number of cells ({width}).")
    try:
        codes = torch.tensor([[int(x) for x in row] for row in rows], dtype=torch.long)
    except ValueError as err:
        raise ValueError(f"Map {name!r}: cells must be integers 0-4 ({err}).") from None
    if ((codes < FREE) | (codes > GOAL2)).any():
        unknown = sorted(set(codes.unique().tolist()) - {FREE, WALL, START, GOAL, GOAL2})
        raise ValueError(f"Map {name!r}: unknown cell code(s) {unknown}.")

    def markers(code: int) -> list[tuple[int, int]]:
        found = [tuple(int(v) for v in pos) for pos in (codes == code).nonzero()]
        if len(found) > 1:
            raise ValueError(f"Map {name!r}: marker {code} appears {len(found)} times (at most once).")
        return found

    start = markers(START)
    goals = markers(GOAL) + markers(GOAL2)
    if markers(GOAL2) and not markers(GOAL):
        raise ValueError(f"Map {name!r}: a second goal (4) needs a first goal (3).")
    return GridMap(
        walls=codes == WALL, start=start[0] if start else None, goals=tuple(goals), rooms=rooms, name=name
    )


def available_maps() -> list[str]:
    """The names of the built-in maps.

    Examples:
        >>> available_maps()
        ['four-rooms', 'three-rooms', 'three-rooms-10x25', 'two-rooms', 'two-rooms-10x20', 'two-rooms-8x20']
    """
    return sorted(_BUILTIN)


def load_map(name_or_path: str | Path | GridMap) -> GridMap:
    """Loads a built-in map by name, or a map file by path.

    Built-in maps are package data (read with :mod:`importlib.resources`, never from the source tree).

    Args:
        name_or_path: a name from :func:`available_maps`, the file name of a built-in map
            (``"four-rooms-15x11.txt"``), a path to a map file, or a :class:`GridMap` (returned as is).

    Raises:
        ValueError: for an unknown name that is not an existing file.

    Examples:
        >>> load_map("two-rooms").shape
        (10, 20)
        >>> load_map("three-rooms").goals
        ((2, 11), (7, 21))
    """
    if isinstance(name_or_path, GridMap):
        return name_or_path
    key = str(name_or_path)
    builtin = _BUILTIN.get(key, key if key in _BUILTIN.values() else None)
    if builtin is not None:
        text = resources.files("torchrl_options.envs").joinpath("maps", builtin).read_text()
        return parse_map(text, name=key.removesuffix(".txt"))
    path = Path(key)
    if path.is_file():
        return parse_map(path.read_text(), name=path.stem)
    raise ValueError(f"Unknown map {key!r}: not a built-in map ({', '.join(available_maps())}) nor a file.")
