"""Gridworld worlds: the record, its validation, its shortest path, and JSONL storage (SPEC 1).

Pure standard library: no I/O beyond `load_worlds` / `save_worlds`, no torch.
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Iterable

Cell = tuple[int, int]

# The one move table. Its order (up, down, left, right) is the order of every listing in the texts.
MOVES: dict[str, Cell] = {"up": (0, 1), "down": (0, -1), "left": (-1, 0), "right": (1, 0)}

# The paper's key order, so `json.dumps(world.to_json())` reproduces its lines byte for byte.
_JSON_KEYS = (
    "world_size_x",
    "world_size_y",
    "wall",
    "pit",
    "start",
    "goal",
    "gridstart_x",
    "gridstart_y",
)


class WorldError(ValueError):
    """A world that breaks SPEC 1 (bad size, misplaced cell, unreachable goal, ambiguous path...)."""


def step(cell: Cell, move: str) -> Cell:
    """The cell reached from `cell` by `move` (no bounds check)."""
    dx, dy = MOVES[move]
    return (cell[0] + dx, cell[1] + dy)


def move_between(a: Cell, b: Cell) -> str:
    """The move that takes `a` to its neighbour `b`."""
    delta = (b[0] - a[0], b[1] - a[1])
    for move, d in MOVES.items():
        if d == delta:
            return move
    raise ValueError(f"{a} and {b} are not neighbours")


@dataclass(frozen=True)
class World:
    """One textualized gridworld, in absolute coordinates. Constructing one validates it."""

    size_x: int
    size_y: int
    x0: int
    y0: int
    walls: tuple[Cell, ...]
    pits: tuple[Cell, ...]
    start: Cell
    goal: Cell

    def __post_init__(self) -> None:
        self._validate_layout()
        if self._path_count_and_parents[0] == 0:
            raise WorldError(f"goal {self.goal} is unreachable from start {self.start}")
        if self._path_count_and_parents[0] > 1:
            raise WorldError(
                f"more than one shortest path from {self.start} to {self.goal}; "
                "a world must have exactly one"
            )
        # Materialise the path now: it is needed by every text and score, and the BFS tables can go.
        self.__dict__["_path"] = self._trace_path()
        del self.__dict__["_path_count_and_parents"]

    @property
    def x1(self) -> int:
        """x of the last (right-most) column."""
        return self.x0 + self.size_x - 1

    @property
    def y1(self) -> int:
        """y of the last (top) row."""
        return self.y0 + self.size_y - 1

    def in_grid(self, cell: Cell) -> bool:
        """Whether `cell` lies inside the X by Y rectangle."""
        x, y = cell
        return self.x0 <= x < self.x0 + self.size_x and self.y0 <= y < self.y0 + self.size_y

    def is_free(self, cell: Cell) -> bool:
        """Whether `cell` is inside the grid and neither a wall nor a pit."""
        return self.in_grid(cell) and not self.padded[self.index(cell)]

    @property
    def stride(self) -> int:
        """Index step of one column in `padded`; the neighbour offsets are +1, -1, -stride, +stride."""
        return self.size_y + 2

    def offsets(self) -> tuple[int, int, int, int]:
        """Index offsets of the up, down, left, right neighbours in `padded` (the MOVES order)."""
        stride = self.size_y + 2
        return (1, -1, -stride, stride)

    def index(self, cell: Cell) -> int:
        """Position of `cell` (inside the grid or its one-cell border) in `padded`."""
        return (cell[0] - self.x0 + 1) * (self.size_y + 2) + cell[1] - self.y0 + 1

    def cell_at(self, index: int) -> Cell:
        """Inverse of `index`."""
        column, row = divmod(index, self.size_y + 2)
        return (column - 1 + self.x0, row - 1 + self.y0)

    @cached_property
    def padded(self) -> bytes:
        """Blocked mask over the grid plus a one-cell border, column-major (see `index`).

        1 marks a wall, a pit or a border cell, so neighbour lookups need no bounds checks;
        graph searches over all worlds run on it.
        """
        stride = self.size_y + 2
        mask = bytearray(b"\x01" * ((self.size_x + 2) * stride))
        for column in range(1, self.size_x + 1):
            mask[column * stride + 1 : column * stride + 1 + self.size_y] = bytes(self.size_y)
        for cell in self.walls + self.pits:
            mask[self.index(cell)] = 1
        return bytes(mask)

    def shortest_path(self) -> list[Cell]:
        """The unique shortest path, start to goal inclusive."""
        return list(self._path)

    def optimal_moves(self) -> list[str]:
        """The moves along the unique shortest path."""
        path = self._path
        return [move_between(a, b) for a, b in zip(path, path[1:])]

    def key(self) -> tuple:
        """Canonical identity for deduplication: obstacle order does not matter, positions do."""
        return (
            self.size_x,
            self.size_y,
            self.x0,
            self.y0,
            tuple(sorted(self.walls)),
            tuple(sorted(self.pits)),
            self.start,
            self.goal,
        )

    @classmethod
    def from_json(cls, obj: dict[str, Any]) -> World:
        """Build (and validate) a world from one parsed line of the paper's schema `{"question": {...}}`."""
        if not isinstance(obj, dict) or not isinstance(obj.get("question"), dict):
            raise WorldError(f"expected an object with key 'question', got {_short(obj)}")
        q = obj["question"]
        missing = [k for k in _JSON_KEYS if k not in q]
        if missing:
            raise WorldError(f"missing keys {missing}; required: {list(_JSON_KEYS)}")
        try:
            return cls(
                size_x=_as_int(q["world_size_x"], "world_size_x"),
                size_y=_as_int(q["world_size_y"], "world_size_y"),
                x0=_as_int(q["gridstart_x"], "gridstart_x"),
                y0=_as_int(q["gridstart_y"], "gridstart_y"),
                walls=tuple(_as_cell(c, "wall") for c in _as_list(q["wall"], "wall")),
                pits=tuple(_as_cell(c, "pit") for c in _as_list(q["pit"], "pit")),
                start=_as_cell(q["start"], "start"),
                goal=_as_cell(q["goal"], "goal"),
            )
        except TypeError as err:
            raise WorldError(str(err)) from err

    def to_json(self) -> dict[str, Any]:
        """The paper's schema, keys in its order, lists not tuples."""
        return {
            "question": {
                "world_size_x": self.size_x,
                "world_size_y": self.size_y,
                "wall": [list(c) for c in self.walls],
                "pit": [list(c) for c in self.pits],
                "start": list(self.start),
                "goal": list(self.goal),
                "gridstart_x": self.x0,
                "gridstart_y": self.y0,
            }
        }

    def _validate_layout(self) -> None:
        for name in ("size_x", "size_y"):
            if getattr(self, name) < 2:
                raise WorldError(f"{name}={getattr(self, name)} is too small; allowed: 2 or more")
        grid = f"({self.x0}, {self.y0})-({self.x1}, {self.y1})"
        seen: dict[Cell, str] = {}
        for kind, cells in (("wall", self.walls), ("pit", self.pits)):
            for cell in cells:
                if not self.in_grid(cell):
                    raise WorldError(f"{kind} {cell} is outside the grid {grid}")
                if cell in seen:
                    raise WorldError(f"{kind} {cell} duplicates a {seen[cell]}; each cell holds one obstacle")
                seen[cell] = kind
        for name in ("start", "goal"):
            cell = getattr(self, name)
            if not self.in_grid(cell):
                raise WorldError(f"{name} {cell} is outside the grid {grid}")
            if cell in seen:
                raise WorldError(f"{name} {cell} is on a {seen[cell]}; it must be a free cell")
        if self.start == self.goal:
            raise WorldError(f"start and goal are both {self.start}; they must differ")

    @cached_property
    def _path_count_and_parents(self) -> tuple[int, list[int]]:
        """BFS from start over `padded`: number of shortest paths to the goal (capped at 2), parents."""
        blocked, offsets = self.padded, self.offsets()
        start, goal = self.index(self.start), self.index(self.goal)
        dist = [-1] * len(blocked)
        count = [0] * len(blocked)
        parent = [-1] * len(blocked)
        dist[start], count[start] = 0, 1
        queue = deque([start])
        while queue:
            i = queue.popleft()
            if i == goal:
                break
            d = dist[i] + 1
            for o in offsets:
                j = i + o
                if blocked[j]:
                    continue
                if dist[j] < 0:
                    dist[j], count[j], parent[j] = d, count[i], i
                    queue.append(j)
                elif dist[j] == d:
                    count[j] = min(2, count[j] + count[i])
        return count[goal], parent

    def _trace_path(self) -> tuple[Cell, ...]:
        parent = self._path_count_and_parents[1]
        path = [self.index(self.goal)]
        start = self.index(self.start)
        while path[-1] != start:
            path.append(parent[path[-1]])
        return tuple(self.cell_at(i) for i in reversed(path))


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _as_int(value: Any, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise WorldError(f"{name} must be an integer, got {_short(value)}")
    return value


def _as_list(value: Any, name: str) -> list:
    if not isinstance(value, list):
        raise WorldError(f"{name} must be a list of [x, y] pairs, got {_short(value)}")
    return value


def _as_cell(value: Any, name: str) -> Cell:
    if not (isinstance(value, (list, tuple)) and len(value) == 2):
        raise WorldError(f"{name} must be an [x, y] pair, got {_short(value)}")
    return (_as_int(value[0], f"{name} x"), _as_int(value[1], f"{name} y"))


def load_worlds(path: str | Path) -> list[World]:
    """Read a JSONL file of worlds; a malformed line raises WorldError naming the file and line."""
    worlds = []
    with open(path, encoding="utf-8") as f:
        for number, line in enumerate(f, start=1):
            if not line.strip():
                continue
            try:
                worlds.append(World.from_json(json.loads(line)))
            except (json.JSONDecodeError, WorldError) as err:
                raise WorldError(f"{path}:{number}: {err}") from err
    return worlds


def save_worlds(path: str | Path, worlds: Iterable[World]) -> None:
    """Write worlds as JSONL in the paper's schema (one `{"question": ...}` per line)."""
    with open(path, "w", encoding="utf-8") as f:
        for world in worlds:
            f.write(json.dumps(world.to_json()) + "\n")
