"""Where a model's answer first departs from the golden one, described so failures can be counted by kind.

`first_wrong_line` walks the golden answer of a world and classifies the first line the model's answer gets
wrong: which section it is in (thought, backtrack, plan), in the thought which BFS step and which expanded
state of that step (its position on the frontier), and what the line is (a step header, a state name, a
neighbour's coordinate or its label). For a wrong label it also says what the neighbour really is (free and
new, already visited, wall, pit, outside the grid) and whether the model wrote ``cut`` for a move or a move
for ``cut``. Nothing here raises on model text.
"""

from __future__ import annotations

from itertools import islice
from dataclasses import asdict, dataclass

from pipeline.core.scoring import _as_text, first_difference
from pipeline.core.texts import golden_answer, is_step_header, parse_cell
from pipeline.core.variants import MAP_VARIANTS
from pipeline.core.world import MOVES, Cell, World, step

_HEADERS = {"Thought:": "thought", "Backtrack:": "backtrack", "Plan:": "plan"}

# What a wrong line is (ErrorSite.line).
LINE_KINDS = ("section header", "step header", "state name", "coordinate", "label", "backtrack", "plan", "end")
# What a neighbour whose label is wrong really is (ErrorSite.neighbour).
NEIGHBOURS = ("free", "visited", "wall", "pit", "outside")


@dataclass(frozen=True)
class ErrorSite:
    """The first wrong line of an answer (0-based ``index`` in the answer's lines) and what it is."""

    index: int
    section: str                  # thought | backtrack | plan | end (the answer stopped or ran on)
    line: str                     # one of LINE_KINDS
    step: int | None = None       # BFS step (1-based) of a thought line
    state: int | None = None      # 0-based position on that step's frontier of the state being expanded
    neighbour: str | None = None  # label lines: one of NEIGHBOURS
    expected: str | None = None   # the golden line
    got: str | None = None        # the model's line (None where the answer ended)
    label_error: str | None = None  # label lines: "move for cut", "cut for move" or "wrong move"

    def to_dict(self) -> dict:
        return asdict(self)


def _levels(world: World, root: Cell) -> dict[Cell, int]:
    """BFS level of every free cell reachable from ``root``."""
    levels, frontier = {root: 0}, [root]
    while frontier:
        following = []
        for cell in frontier:
            for move in MOVES:
                nxt = step(cell, move)
                if nxt not in levels and world.is_free(nxt):
                    levels[nxt] = levels[cell] + 1
                    following.append(nxt)
        frontier = following
    return levels


def _neighbour_kind(world: World, cell: Cell | None, levels: dict[Cell, int], bfs_step: int) -> str | None:
    """What a neighbour written at BFS step ``bfs_step`` is (NEIGHBOURS); ``levels``: `_levels` from the root."""
    if cell is None:
        return None
    if not world.in_grid(cell):
        return "outside"
    if cell in world.walls:
        return "wall"
    if cell in world.pits:
        return "pit"
    # Step k expands the states of level k-1: their free neighbours are new (level k) or visited (k-2).
    return "free" if levels.get(cell) == bfs_step else "visited"


def _label_error(expected: str, got: str | None) -> str | None:
    if got is None:
        return None
    if expected == "cut" and got in MOVES:
        return "move for cut"
    if expected in MOVES and got == "cut":
        return "cut for move"
    return "wrong move" if expected in MOVES and got in MOVES else None


def _walk(golden: list[str]):
    """Each golden line's place: (section, line kind, BFS step or None, lines so far in this step's neighbour
    lists, ``From`` lines so far in this step minus one). The one reading of a golden answer's structure."""
    section, bfs_step, in_step, named_states = "", None, 0, -1
    for line in golden:
        if line in _HEADERS:
            section, kind = _HEADERS[line], "section header"
        elif section == "thought" and is_step_header(line):
            bfs_step, in_step, named_states, kind = (bfs_step or 0) + 1, 0, -1, "step header"
        elif section == "thought" and line.startswith("From "):
            named_states, kind = named_states + 1, "state name"
        elif section == "thought":
            kind = "coordinate" if in_step % 2 == 0 else "label"
            in_step += 1
        else:
            kind = section
        yield section, kind, bfs_step, in_step, named_states


def first_wrong_line(world: World, direction: str, variant: str, text: object, steps: str = "numbered",
                     plan: str = "moves") -> ErrorSite | None:
    """The first line of ``text`` that departs from the golden optimal-setting answer, classified; None if
    the answer is the golden one. ``direction`` and ``variant`` are checked like `texts.answer`'s."""
    golden = golden_answer(world, direction, variant, "optimal", steps=steps, plan=plan).split("\n")
    produced = _as_text(text).split("\n")
    index = first_difference(produced, golden)
    if index is None:
        return None
    got = produced[index] if index < len(produced) else None
    if index >= len(golden):
        return ErrorSite(index, "end", "end", got=got)
    switches = MAP_VARIANTS.get(variant)
    section, kind, bfs_step, in_step, named_states = next(islice(_walk(golden), index, None))
    state = None
    expected = golden[index]
    if section == "thought" and kind in ("coordinate", "label", "state name"):
        if switches is not None and switches.named:
            state = max(named_states, 0)
        elif switches is not None and switches.all_moves:
            state = (in_step - 1) // 8   # four neighbours a state, two lines each
    neighbour = label_error = None
    if kind == "label":
        root = world.start if direction == "fwd" else world.goal
        neighbour = _neighbour_kind(world, parse_cell(golden[index - 1]), _levels(world, root), bfs_step or 0)
        label_error = _label_error(expected, got)
    return ErrorSite(index, section, kind, bfs_step if section == "thought" else None, state, neighbour,
                     expected, got, label_error)


def label_kinds(world: World, direction: str, variant: str, steps: str = "numbered", plan: str = "moves"
                ) -> list[tuple[int, str]]:
    """Every label line of the golden optimal-setting thought as (0-based line index, what its neighbour is:
    one of NEIGHBOURS): what a teacher-forced probe grades the model's labels by."""
    return [(index, kind) for index, kind, _ in label_cells(world, direction, variant, steps, plan)]


def label_cells(world: World, direction: str, variant: str, steps: str = "numbered", plan: str = "moves"
                ) -> list[tuple[int, str, Cell]]:
    """`label_kinds` with the neighbour each label is about: (line index, what it is, its cell)."""
    golden = golden_answer(world, direction, variant, "optimal", steps=steps, plan=plan).split("\n")
    levels = _levels(world, world.start if direction == "fwd" else world.goal)
    labels = [(index, parse_cell(golden[index - 1]), bfs_step)
              for index, (_, kind, bfs_step, _, _) in enumerate(_walk(golden)) if kind == "label"]
    return [(index, _neighbour_kind(world, cell, levels, bfs_step), cell) for index, cell, bfs_step in labels]


def corner_offset(world: World, cell: Cell) -> int:
    """How far ``cell`` lies from the grid's low corner: the larger of x - x0 and y - y0. A grid of side s holds
    offsets up to s - 1, so no cell inside a training world of sides up to 4 lies at offset 4 or more."""
    return max(cell[0] - world.x0, cell[1] - world.y0)


# What `line_kinds` calls a golden line: LINE_KINDS' thought and section kinds, with a Backtrack line split into
# the cell it is at and the move it takes from there, and an anchored Plan's cells apart from its moves.
PROBE_KINDS = ("section header", "step header", "state name", "coordinate", "label", "backtrack cell",
               "backtrack move", "plan cell", "plan")


def line_kinds(world: World, direction: str, variant: str, steps: str = "numbered", plan: str = "moves"
               ) -> list[tuple[str, int | None]]:
    """Every line of the golden optimal-setting answer as (one of PROBE_KINDS, the move's 0-based index in its
    section for a backtrack move or plan line, else None): what a teacher-forced probe grades lines by."""
    golden = golden_answer(world, direction, variant, "optimal", steps=steps, plan=plan).split("\n")
    kinds, moves = [], {"backtrack": 0, "plan": 0}
    for line, (_, kind, *_) in zip(golden, _walk(golden)):
        if kind in moves and parse_cell(line) is not None:
            kinds.append((f"{kind} cell", None))
        elif kind in moves:
            kinds.append(("backtrack move" if kind == "backtrack" else "plan", moves[kind]))
            moves[kind] += 1
        else:
            kinds.append((kind, None))
    return kinds


# Buckets of the BFS step a wrong thought line is in (ErrorSite.step).
STEP_BUCKETS = ("step 1", "step 2", "steps 3-5", "steps 6+")


def category(site: dict | ErrorSite) -> str:
    """A short name for the kind of a first wrong line: its line kind, and for a label what went wrong."""
    site = site.to_dict() if isinstance(site, ErrorSite) else site
    if site["line"] == "label":
        return f"label: {site['label_error'] or 'other'}"
    return str(site["line"])


def step_bucket(bfs_step: int | None) -> str | None:
    """Which of STEP_BUCKETS a BFS step falls in (None outside the thought)."""
    if bfs_step is None:
        return None
    return STEP_BUCKETS[0] if bfs_step <= 1 else STEP_BUCKETS[1] if bfs_step == 2 else \
        STEP_BUCKETS[2] if bfs_step <= 5 else STEP_BUCKETS[3]
