"""Gridworld worlds: the record, its validation, its shortest path, and JSONL storage (docs/spec.md §1).

Pure standard library: no I/O beyond `load_worlds` / `save_worlds`, no torch.
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from collections.abc import Iterable

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


# Codes in `World.padded`; any nonzero code blocks a move.
_WALL, _PIT, _BORDER = 1, 2, 3
_KINDS = {_WALL: "wall", _PIT: "pit"}


class WorldError(ValueError):
    """A world that breaks docs/spec.md §1 (bad size, misplaced cell, unreachable goal, ambiguous path...)."""


def step(cell: Cell, move: str) -> Cell:
    """The cell reached from `cell` by `move` (no bounds check)."""
    try:
        dx, dy = MOVES[move]
    except KeyError:
        raise ValueError(f"unknown move {move!r}; allowed: {', '.join(MOVES)}") from None
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
    # Derived once at construction (this runs for 50k+ worlds, and every text and score needs them):
    # `padded` is the obstacle mask over the grid and a one-cell border, column-major (see `index`),
    # nonzero for a wall, pit or border cell, so neighbour lookups need no bounds checks.
    padded: bytes = field(init=False, repr=False, compare=False)
    _path: tuple[Cell, ...] = field(init=False, repr=False, compare=False)
    _moves: tuple[str, ...] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "padded", self._build_mask())
        paths, parent = self._count_shortest_paths()
        if paths == 0:
            raise WorldError(f"goal {self.goal} is unreachable from start {self.start}")
        if paths > 1:
            raise WorldError(
                f"more than one shortest path from {self.start} to {self.goal}; a world must have exactly one"
            )
        path, moves = self._trace_path(parent)
        object.__setattr__(self, "_path", path)
        object.__setattr__(self, "_moves", moves)

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
        # Inlined (not in_grid + index): this is the inner call of observations and walks.
        dx, dy = cell[0] - self.x0, cell[1] - self.y0
        return (
            0 <= dx < self.size_x
            and 0 <= dy < self.size_y
            and not self.padded[(dx + 1) * (self.size_y + 2) + dy + 1]
        )

    def offsets(self) -> tuple[int, int, int, int]:
        """Index offsets of the up, down, left, right neighbours in `padded` (the MOVES order)."""
        stride = self.size_y + 2
        return (1, -1, -stride, stride)

    def index(self, cell: Cell) -> int:
        """Position of `cell` (inside the grid or its one-cell border) in `padded`."""
        return (cell[0] - self.x0 + 1) * (self.size_y + 2) + cell[1] - self.y0 + 1

    def shortest_path(self) -> list[Cell]:
        """The unique shortest path, start to goal inclusive."""
        return list(self._path)

    def optimal_moves(self) -> list[str]:
        """The moves along the unique shortest path."""
        return list(self._moves)

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

    def _build_mask(self) -> bytes:
        """Validate sizes and cell placement while building `padded` (codes: _WALL, _PIT, _BORDER)."""
        for name in ("size_x", "size_y"):
            if getattr(self, name) < 2:
                raise WorldError(f"{name}={getattr(self, name)} is too small; allowed: 2 or more")
        size_x, size_y, x0, y0 = self.size_x, self.size_y, self.x0, self.y0
        stride = size_y + 2
        mask = bytearray([_BORDER]) * ((size_x + 2) * stride)
        for column in range(1, size_x + 1):
            mask[column * stride + 1 : column * stride + 1 + size_y] = bytes(size_y)
        for code, cells in ((_WALL, self.walls), (_PIT, self.pits)):
            for cell in cells:
                dx, dy = cell[0] - x0, cell[1] - y0
                if not (0 <= dx < size_x and 0 <= dy < size_y):
                    raise WorldError(f"{_KINDS[code]} {cell} is outside the grid {self._grid_text()}")
                i = (dx + 1) * stride + dy + 1
                if mask[i]:
                    raise WorldError(
                        f"{_KINDS[code]} {cell} duplicates a {_KINDS[mask[i]]}; each cell holds one obstacle"
                    )
                mask[i] = code
        for name in ("start", "goal"):
            cell = getattr(self, name)
            if not self.in_grid(cell):
                raise WorldError(f"{name} {cell} is outside the grid {self._grid_text()}")
            if mask[self.index(cell)]:
                raise WorldError(
                    f"{name} {cell} is on a {_KINDS[mask[self.index(cell)]]}; it must be a free cell"
                )
        if self.start == self.goal:
            raise WorldError(f"start and goal are both {self.start}; they must differ")
        return bytes(mask)

    def _grid_text(self) -> str:
        return f"({self.x0}, {self.y0})-({self.x1}, {self.y1})"

    def _count_shortest_paths(self) -> tuple[int, list[int]]:
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

    def _trace_path(self, parent: list[int]) -> tuple[tuple[Cell, ...], tuple[str, ...]]:
        """Path cells and moves, start to goal, from the BFS parents."""
        move_of_offset = dict(zip(self.offsets(), MOVES))
        indices = [self.index(self.goal)]
        start = self.index(self.start)
        while indices[-1] != start:
            indices.append(parent[indices[-1]])
        indices.reverse()
        moves = tuple(move_of_offset[b - a] for a, b in zip(indices, indices[1:]))
        cells = [self.start]
        for move in moves:
            cells.append(step(cells[-1], move))
        return tuple(cells), moves


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


# Loading refuses worlds larger than this many cells before allocating their mask (the paper's are <= 400).
MAX_CELLS = 1_000_000


def load_worlds(path: str | Path) -> list[World]:
    """Read a JSONL file of worlds; a malformed line raises WorldError naming the file and line."""
    worlds = []
    with open(path, "rb") as f:
        for number, raw in enumerate(f, start=1):
            try:
                line = raw.decode("utf-8")
                if not line.strip():
                    continue
                obj = json.loads(line)
                _check_size(obj)
                worlds.append(World.from_json(obj))
            except UnicodeDecodeError as err:
                raise WorldError(f"{path}:{number}: not UTF-8 text ({err.reason} at byte {err.start})") from err
            except (json.JSONDecodeError, WorldError) as err:
                raise WorldError(f"{path}:{number}: {err}") from err
    return worlds


def _check_size(obj: Any) -> None:
    """Refuse an absurd size before `World` allocates a mask for it (a typo must not exhaust memory)."""
    question = obj.get("question") if isinstance(obj, dict) else None
    if not isinstance(question, dict):
        return
    x, y = question.get("world_size_x"), question.get("world_size_y")
    if isinstance(x, int) and isinstance(y, int) and x > 0 and y > 0 and x * y > MAX_CELLS:
        raise WorldError(f"world_size_x={x}, world_size_y={y}: {x * y} cells; allowed: at most {MAX_CELLS}")


def save_worlds(path: str | Path, worlds: Iterable[World]) -> None:
    """Write worlds as JSONL in the paper's schema (one `{"question": ...}` per line)."""
    with open(path, "w", encoding="utf-8") as f:
        for world in worlds:
            f.write(json.dumps(world.to_json()) + "\n")
