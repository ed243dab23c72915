"""The texts of a world: task prompt, observations, cognitive maps and answers, conversations (docs/spec.md §2-3)."""

from __future__ import annotations

import random
import re
from functools import lru_cache, cache

from pipeline.core.variants import DIRECTIONS, MAP_VARIANTS, VARIANTS, check, check_choice
from pipeline.core.world import MOVES, Cell, World, move_between, step

# What a model is prompted with: the paper's three turns (instruction, "OK", task), the task turn alone, or
# the task turn alone with the grid's free cells listed too ("cells", not in the paper). The instruction is
# the same English text in every conversation: a model trained from scratch learns nothing from it, yet pays
# for its tokens in every step; pretrained models keep the paper's prompt. The paper lists only the pits and
# walls, so a free cell is known by no match among them; "cells" lists the free cells too, so every cell
# of the grid is known by a match (the lookup a label needs stays a lookup as the lists grow). "axes" (not in
# the paper) lists the grid's columns and rows after its bounds, each in an order drawn from the world alone, so
# whether a cell lies inside the grid is a match of its x among the columns and its y among the rows, not a
# comparison with the bounds: training grids (sides 2-4) never hold a cell 4 or more from their low corner, so
# "beyond the bound" and "4 from the corner" agree on every training world, while a match is the same rule at
# any size.
PROMPTS: tuple[str, ...] = ("paper", "task", "cells", "axes")
# The job's default (`ModelSettings.prompt`) and every signature's: the task turn alone, for the models trained
# from scratch; the paper-scale presets choose "paper".
DEFAULT_PROMPT = "task"

# How a map's (and CoT's) step headers are written: the paper's `Step k:`, or `Step:` with no number
# (not in the paper). A model trained from scratch learns the number words only up to the longest training
# map, so a larger test world would need words it never saw; plain headers hold no such word.
STEP_HEADERS: tuple[str, ...] = ("numbered", "plain")

# How an optimal answer's Plan is written: the paper's moves alone, one a line, or "anchored" (not in the paper):
# the cell the walk is at before each move and the goal after the last, as a bwd Backtrack writes them
# (start, move, cell, move, ..., goal). A run of equal moves copied from the Backtrack is then a lookup of the
# cell just written, not a count of identical lines, and a larger world's runs are longer than any training
# world's. Only answers with a Thought have it: NONE and DFS keep the paper's Plan.
PLAN_FORMS: tuple[str, ...] = ("moves", "anchored")


def step_header(level: int, steps: str = "numbered") -> str:
    """The header line of BFS step ``level`` (1-based): `Step k:` (numbered) or `Step:` (plain)."""
    return f"Step {level}:" if steps == "numbered" else "Step:"


def is_step_header(line: str) -> bool:
    """Whether a Thought line is a step header, in either form."""
    return line == "Step:" or (line.startswith("Step ") and line.endswith(":"))

INSTRUCTION = (
    "You are given a rectangular gridworld, where you can move up, down, left, or right as long as each of "
    "your x, y coordinates are within 0 to the x, y size of the grid. If you move up, your y coordinate "
    "increases by 1. If you move down, your y coordinate decreases by 1. If you move left, your x coordinate "
    "decreases by 1. If you move right, your x coordinate increases by 1.\n\nYou will interact with the "
    "gridworld environment to reach the goal state, while avoiding the pit and the wall. You cannot move "
    "through the wall or move outside the grid. If you fall into the pit, you lose. If you reach the goal, "
    "you win. For each of your turn, you will be given the possible moves.\n\nYou should respond your move "
    "with either one of 'up', 'down', 'left', or 'right'."
)
ACKNOWLEDGEMENT = "OK"

# BWD labels a neighbour by the move from it back to the state: the opposite move.
_OPPOSITE = {"up": "down", "down": "up", "left": "right", "right": "left"}
_LABELS: dict[str, tuple[str, ...]] = {
    "fwd": tuple(MOVES),
    "bwd": tuple(_OPPOSITE[m] for m in MOVES),
}


@lru_cache(maxsize=4096)
def cell_text(cell: Cell) -> str:
    """`(x, y)` as every text writes a cell."""
    return f"({cell[0]}, {cell[1]})"


_CELL_TEXT = re.compile(r"\((-?\d+), (-?\d+)\)")


def parse_cell(text: str) -> Cell | None:
    """The cell a `cell_text` line (or cell word) names, or None for any other text."""
    match = _CELL_TEXT.fullmatch(text)
    return (int(match.group(1)), int(match.group(2))) if match else None


def _listing(kind: str, cells: tuple[Cell, ...]) -> str:
    if not cells:
        return f"There is no {kind}."
    texts = [cell_text(c) for c in cells]
    if len(texts) == 1:
        return f"The {kind} is at {texts[0]}."
    return f"The {kind} is at {', '.join(texts[:-1])}, and {texts[-1]}."


def free_cells(world: World) -> tuple[Cell, ...]:
    """The grid's free cells (neither wall nor pit), start and goal included, in an order drawn from the world
    alone (the obstacle lists are in no spatial order either, so a list position tells nothing)."""
    cells = [(x, y) for x in range(world.x0, world.x1 + 1) for y in range(world.y0, world.y1 + 1)
             if world.is_free((x, y))]
    random.Random(f"free:{world.x0},{world.y0},{world.x1},{world.y1},{world.walls},{world.pits}").shuffle(cells)
    return tuple(cells)


# (pits, walls) in the order a prompt lists them.
Obstacles = tuple[tuple[Cell, ...], tuple[Cell, ...]]


def listed_obstacles(world: World, distractors: int = 0, frame: int = 0) -> Obstacles:
    """(pits, walls) as a prompt lists them: the world's own, or (``distractors`` > 0, for training texts; not in
    the paper) with up to that many cells of the ``frame`` x ``frame`` square that lie outside the grid put in
    too, each in one of the two lists at a random place. They change nothing the answer says (a cell outside
    the grid is `cut` anyway) and make the lists as long as a larger world's, so the lookup a label needs is
    trained on long lists. How many and which are drawn from the world alone."""
    if not distractors:
        return world.pits, world.walls
    rng = random.Random(f"distractors:{distractors}:{frame}:{world.key()}")
    outside = [(x, y) for x in range(frame) for y in range(frame)
               if not (world.x0 <= x <= world.x1 and world.y0 <= y <= world.y1)]
    pits, walls = list(world.pits), list(world.walls)
    for cell in rng.sample(outside, min(rng.randint(0, distractors), len(outside))):
        listed = pits if rng.random() < 0.5 else walls
        listed.insert(rng.randint(0, len(listed)), cell)
    return tuple(pits), tuple(walls)


def grid_axes(world: World) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The grid's columns (x values) and rows (y values), each in an order drawn from the world alone (so a
    list position tells nothing, as in `free_cells`)."""
    rng = random.Random(f"axes:{world.x0},{world.y0},{world.x1},{world.y1}")
    columns, rows = list(range(world.x0, world.x1 + 1)), list(range(world.y0, world.y1 + 1))
    rng.shuffle(columns)
    rng.shuffle(rows)
    return tuple(columns), tuple(rows)


def task_text(world: World, prompt: str = DEFAULT_PROMPT, obstacles: Obstacles | None = None) -> str:
    """The task part of the third human turn (docs/spec.md §2.3), ending in a newline; the observation follows.
    ``prompt`` (`PROMPTS`): "cells" lists the free cells after the walls, "axes" the grid's columns and rows
    after its bounds (neither is in the paper); the others write the paper's task. ``obstacles``: the (pits,
    walls) lists to write instead of the world's own (`listed_obstacles`)."""
    pits, walls = obstacles or (world.pits, world.walls)
    listed = f" {_listing('free cell', free_cells(world))}" if prompt == "cells" else ""
    axes = ""
    if prompt == "axes":
        columns, rows = grid_axes(world)
        axes = f" Columns: {', '.join(map(str, columns))}. Rows: {', '.join(map(str, rows))}."
    return (
        f"Grid is from {cell_text((world.x0, world.y0))} to {cell_text((world.x1, world.y1))}.{axes} "
        f"Goal: {cell_text(world.goal)}\n"
        f"Current: {cell_text(world.start)}\n"
        f"{_listing('pit', pits)} {_listing('wall', walls)}{listed}\n"
    )


def observation(world: World, cell: Cell) -> str:
    """What the agent sees at `cell`: its position and the free neighbours, in the MOVES order (docs/spec.md §2.4)."""
    lines = ["Current:", cell_text(cell), "Possible:"]
    for move in MOVES:
        target = step(cell, move)
        if world.is_free(target):
            lines += (cell_text(target), move)
    return "\n".join(lines)


def first_human_text(world: World, prompt: str = DEFAULT_PROMPT, obstacles: Obstacles | None = None) -> str:
    """The full third turn: task text (``prompt`` and ``obstacles``: see `task_text`) then the observation at
    the start."""
    return task_text(world, prompt, obstacles) + observation(world, world.start)


def prompt_turns(world: World, prompt: str = DEFAULT_PROMPT, obstacles: Obstacles | None = None) -> list[dict[str, str]]:
    """What a model is prompted with: the paper's three turns (``prompt="paper"``), the task turn alone
    (``"task"``, the default), or the task turn alone with the free cells (``"cells"``) or the grid's columns and
    rows (``"axes"``) listed. ``obstacles``:
    the (pits, walls) lists to write instead of the world's own (`listed_obstacles`)."""
    check_choice("prompt", prompt, PROMPTS)
    task = {"from": "human", "value": first_human_text(world, prompt, obstacles)}
    if prompt != "paper":
        return [task]
    return [{"from": "human", "value": INSTRUCTION}, {"from": "gpt", "value": ACKNOWLEDGEMENT}, task]


def cognitive_map(
    world: World, direction: str, *, all_moves: bool, marking: bool, backtrack: bool, named: bool = False,
    steps: str = "numbered",
) -> list[str]:
    """The Thought section of a map variant, `Thought:` first: BFS steps, then Backtrack if switched on.

    BFS runs level by level from the start (fwd) or the goal (bwd) until the other end is visited;
    a neighbour is new if free and not visited before this step (docs/spec.md §3). With ``named`` (not in the
    paper) each expanded state's neighbours follow a ``From (x, y):`` line naming it; ``steps`` is how the
    step headers are written (`STEP_HEADERS`).
    """
    check_choice("direction", direction, DIRECTIONS)
    check_choice("steps", steps, STEP_HEADERS)
    root, target = (world.start, world.goal) if direction == "fwd" else (world.goal, world.start)
    blocked, offsets, labels = world.padded, world.offsets(), _LABELS[direction]
    moves = tuple(zip(offsets, labels))
    names = _padded_names(world)
    visited = bytearray(len(blocked))
    queued = bytearray(len(blocked))
    root_i, target_i = world.index(root), world.index(target)
    visited[root_i] = 1
    frontier = [root_i]
    lines = ["Thought:"]
    level = 0
    while not visited[target_i]:
        level += 1
        lines.append(step_header(level, steps))
        following = []
        for state in frontier:
            if named:
                lines.append(f"From {names[state]}:")
            for offset, label in moves:
                j = state + offset
                if not blocked[j] and not visited[j]:
                    lines += (names[j], label)
                    if not queued[j]:
                        queued[j] = 1
                        following.append(j)
                elif all_moves:
                    lines += (names[j], "cut" if marking else label)
        for j in following:
            visited[j] = 1
        frontier = following
    if backtrack:
        lines += backtrack_lines(world, direction)
    return lines


def edge_label_spans(world: World, answer: str, largest: tuple[int, int]) -> list[tuple[int, int]]:
    """(start, end) character spans in ``answer`` of the labels whose neighbour lies just outside the grid
    along an axis on which the grid is as long as the largest train grid (``largest``: sides X, Y).

    A grid of side at most L holds no cell L or more from its low (or high) corner, so such a neighbour's `cut`
    is explained as well by "beyond the grid's bound" as by "L cells from the opposite corner", and the train
    worlds never tell the two rules apart; a larger world does (docs/extrapolation.md).
    `DataSettings.mask_edge_labels` (not in the paper) leaves these labels out of the loss. Only neighbour
    lines name cells outside the grid, so every such cell line's next line is its label."""
    lines = answer.split("\n")
    starts = [0]
    for line in lines:
        starts.append(starts[-1] + len(line) + 1)
    spans = []
    for i, line in enumerate(lines[:-1]):
        cell = parse_cell(line)
        if cell is None or world.in_grid(cell):
            continue
        x, y = cell
        across_x = not world.x0 <= x <= world.x1
        if (world.size_x if across_x else world.size_y) == largest[0 if across_x else 1]:
            spans.append((starts[i + 1], starts[i + 1] + len(lines[i + 1])))
    return spans


def _padded_names(world: World) -> list[str]:
    """`cell_text` of every cell of the padded grid, by `World.index` (the map prints border cells too)."""
    low, high = world.y0 - 1, world.y1 + 2
    columns = range(world.x0 - 1, world.x1 + 2)
    if low < _COLUMN_LOW or high > _COLUMN_HIGH:
        return [cell_text((x, y)) for x in columns for y in range(low, high)]
    names: list[str] = []
    for x in columns:
        names += _column_names(x)[low - _COLUMN_LOW : high - _COLUMN_LOW]
    return names


# Cell names are built once per column and sliced per world: a frame holds few distinct cells.
_COLUMN_LOW, _COLUMN_HIGH = -1, 64


@cache
def _column_names(x: int) -> tuple[str, ...]:
    return tuple(cell_text((x, y)) for y in range(_COLUMN_LOW, _COLUMN_HIGH))


def backtrack_lines(world: World, direction: str) -> list[str]:
    """`Backtrack:` then the path as cell/move lines: goal to start for fwd, start to goal for bwd."""
    check_choice("direction", direction, DIRECTIONS)
    path, moves = world.shortest_path(), world.optimal_moves()
    cells = [cell_text(c) for c in path]
    lines = ["Backtrack:"]
    if direction == "fwd":
        for k in range(len(moves), 0, -1):
            lines += (cells[k], moves[k - 1])
        lines.append(cells[0])
    else:
        for k, move in enumerate(moves):
            lines += (cells[k], move)
        lines.append(cells[-1])
    return lines


def cot_thought(world: World, direction: str, steps: str = "numbered") -> list[str]:
    """The CoT baseline's Thought: empty `Step k:` headers, one per optimal move, then Backtrack."""
    check_choice("steps", steps, STEP_HEADERS)
    headers = [step_header(k, steps) for k in range(1, len(world.shortest_path()))]
    return ["Thought:", *headers, *backtrack_lines(world, direction)]


def thought_lines(world: World, direction: str, variant: str, steps: str = "numbered") -> list[str]:
    """The Thought section (with Backtrack) of any variant; empty for `none` and `dfs`. ``steps``: how step
    headers are written (`STEP_HEADERS`)."""
    check_choice("variant", variant, VARIANTS)
    if variant in MAP_VARIANTS:
        return cognitive_map(world, direction, **MAP_VARIANTS[variant]._asdict(), steps=steps)
    if variant == "cot":
        return cot_thought(world, direction, steps)
    check_choice("direction", direction, DIRECTIONS)
    return []


def dfs_moves(world: World, seed: int = 0) -> list[str]:
    """A randomized depth-first walk from start to goal (the `dfs` baseline), the same for the same seed.

    At each cell: go to a random free neighbour not visited yet; with none left, step back towards the
    start along the walk's own tree.
    """
    rng = random.Random(seed)
    parent: dict[Cell, Cell] = {}
    visited = {world.start}
    cell = world.start
    moves = []
    while cell != world.goal:
        targets = ((m, step(cell, m)) for m in MOVES)
        fresh = [(m, t) for m, t in targets if world.is_free(t) and t not in visited]
        if fresh:
            move, nxt = rng.choice(fresh)
            parent[nxt] = cell
            visited.add(nxt)
        else:
            nxt = parent[cell]
            move = move_between(cell, nxt)
        moves.append(move)
        cell = nxt
    return moves


def _moves(world: World, variant: str, seed: int) -> list[str]:
    return dfs_moves(world, seed) if variant == "dfs" else world.optimal_moves()


def golden_answer(world: World, direction: str, variant: str, mode: str, seed: int = 0, steps: str = "numbered",
                  plan: str = "moves") -> str:
    """The first gpt answer: the Thought section, then `Plan:` and all moves (``plan``: `PLAN_FORMS`), or
    `Action:` and the first."""
    check(direction, variant, mode)
    return _answer(world, direction, variant, mode, _moves(world, variant, seed), steps, plan)


def plan_lines(world: World, moves: list[str], plan: str = "moves") -> list[str]:
    """The Plan section's lines for ``moves`` from the start: the moves, or (``plan="anchored"``) the cell before
    each move and the cell after the last."""
    check_choice("plan", plan, PLAN_FORMS)
    if plan == "moves":
        return list(moves)
    cell, lines = world.start, [cell_text(world.start)]
    for move in moves:
        cell = step(cell, move)
        lines += (move, cell_text(cell))
    return lines


def _answer(world: World, direction: str, variant: str, mode: str, moves: list[str], steps: str,
            plan: str = "moves") -> str:
    check_choice("plan", plan, PLAN_FORMS)
    thought = thought_lines(world, direction, variant, steps)
    tail = ["Plan:", *plan_lines(world, moves, plan if thought else "moves")] if mode == "optimal" else \
        ["Action:", moves[0]]
    return "\n".join(thought + tail)


def conversation(
    world: World, direction: str, variant: str, mode: str, seed: int = 0, prompt: str = DEFAULT_PROMPT,
    steps: str = "numbered", obstacles: Obstacles | None = None, plan: str = "moves",
) -> list[dict[str, str]]:
    """The whole training conversation (docs/spec.md §2): prompt, first answer and, when reachable, the walk.
    ``prompt``, ``steps`` and ``plan`` choose the prompt form (`PROMPTS`), the step headers (`STEP_HEADERS`) and
    the Plan's lines (`PLAN_FORMS`);
    ``obstacles`` the prompt's (pits, walls) lists if not the world's own (`listed_obstacles`)."""
    check(direction, variant, mode)
    moves = _moves(world, variant, seed)
    turns = prompt_turns(world, prompt, obstacles)
    turns.append({"from": "gpt", "value": _answer(world, direction, variant, mode, moves, steps, plan)})
    if mode == "reachable":
        cell = step(world.start, moves[0])
        for move in moves[1:]:
            turns.append({"from": "human", "value": observation(world, cell)})
            turns.append({"from": "gpt", "value": move})
            cell = step(cell, move)
    return turns
