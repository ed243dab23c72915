"""The paper's generator ("paper"): world generation as the paper's released code does it
(kaistAI/language_extrapolation, envs/gridworld/data/make_jsonl.py), seeded, bounded, standard library only.

Two things set it apart from the project's generator (`generators.project`):

1. The tree search backtracks. The tree grows one cell at a time, each cell drawn uniformly from the
   cells touching exactly one tree cell, until the goal joins. When no cell can be added, the paper
   removes the cell added last and forbids that cell as a choice at every node still on the search
   stack (its parent *and all earlier nodes*, not the parent only), then chooses again there: a
   depth-first search over the choices, pruned by those removals. It does not stop early when the goal
   touches two tree cells (and so can never join): the whole subtree below is searched and undone
   first. The project generator restarts from scratch instead; the shape distributions differ.
2. The wall and pit lists follow the iteration order of a CPython `set`: the paper adds every cell of
   the un-offset grid column by column, discards start and goal, takes the set difference with the
   tree's cells and walks the result, drawing pit-or-wall per cell; the offset is added afterwards.
   `paper_list_order` rebuilds that set the same way, which reproduces the released test file's order in
   3,000 of 3,000 worlds. (A plain `set(obstacles)` does not: its table size and collision history differ,
   and it matches only about 60% of them.) The order relies on CPython's set layout and its tuple hash,
   which does not depend on PYTHONHASHSEED for tuples of ints.

Bound. The paper's search can run for minutes on some 20 x 20 draws. Here one attempt may backtrack
at most `max_backtracks` times (`MAX_BACKTRACKS` by default); past that, the attempt is abandoned and a
fresh search is started, for the same world size, from the same `rng`. Abandoning conditions on the
search finishing within the bound, so it biases the shapes of the rare worlds that hit it (with
`max_backtracks=0` the process is exactly the project generator's restart process). The search's length
is heavy-tailed: how often the bound is hit at each size is in the README (Configuration, the paper's
generator).

Random draws. The paper draws X, Y, p_pit, then the tree, then per obstacle cell pit-or-wall, then the
offset; this module draws in the same order. Its RNG stream is unseeded and cannot be matched; only the
distribution (and the list order, exactly) are reproduced.
"""

from __future__ import annotations

import random

from pipeline.core.generators.base import GeneratorConfig, neighbour_table, register
from pipeline.core.world import Cell, World

# Backtracks one tree search may make before it is abandoned (see the module docstring).
MAX_BACKTRACKS = 100_000


@register("paper")
def sample_world_paper(
    rng: random.Random, cfg: GeneratorConfig, max_backtracks: int = MAX_BACKTRACKS
) -> World:
    """One world drawn as the paper draws it: sizes and p_pit, a backtracking tree search, obstacles in
    the paper's set order (pit with probability p_pit, else wall), then the offset. All randomness comes
    from `rng`; the same `rng` state gives the same world."""
    if max_backtracks < 0:
        raise ValueError(f"max_backtracks={max_backtracks} is not allowed: need 0 or more")
    size_x = rng.randint(*cfg.size_x)
    size_y = rng.randint(*cfg.size_y)
    p_pit = rng.uniform(*cfg.p_pit)
    tree = None
    while tree is None:
        # An abandoned search (over the bound) is replaced by a fresh one, the stream continuing.
        tree = paper_tree(rng, size_x, size_y, max_backtracks)
    obstacles = [(i // size_y, i % size_y) for i, in_tree in enumerate(tree) if not in_tree]
    walls: list[Cell] = []
    pits: list[Cell] = []
    # The paper draws pit-or-wall while walking its set, so the draws follow the set order too.
    for x, y in paper_list_order(obstacles, size_x, size_y):
        (pits if rng.random() < p_pit else walls).append((x, y))
    x0 = rng.randint(0, cfg.frame - size_x)
    y0 = rng.randint(0, cfg.frame - size_y)
    return World(
        size_x=size_x,
        size_y=size_y,
        x0=x0,
        y0=y0,
        walls=tuple((x0 + x, y0 + y) for x, y in walls),
        pits=tuple((x0 + x, y0 + y) for x, y in pits),
        start=(x0, y0),
        goal=(x0 + size_x - 1, y0 + size_y - 1),
    )


def paper_list_order(
    cells: list[Cell] | tuple[Cell, ...], size_x: int, size_y: int, x0: int = 0, y0: int = 0
) -> list[Cell]:
    """`cells` (the obstacle cells of an X by Y world at offset (x0, y0), absolute, any order) in the
    order the paper lists them: that of its un-offset set, built as the paper builds it.

    Walls and pits are the two parts of one walk over that set, so each list is the subsequence of this
    order holding its cells (see `paper_order`). The result depends on the grid size as well as on the
    cells: the set's table grows with the full grid and shrinks to the obstacles only through the
    difference, so both steps are replayed rather than taking `set(cells)`.
    """
    relative = {(x - x0, y - y0) for x, y in cells}
    grid: set[Cell] = set()
    for x in range(size_x):  # insertion order (column by column) sets the collision history
        for y in range(size_y):
            grid.add((x, y))
    grid.discard((0, 0))
    grid.discard((size_x - 1, size_y - 1))
    free = {c for c in grid if c not in relative}
    free.add((0, 0))
    free.add((size_x - 1, size_y - 1))
    remaining = grid - free  # only len(free) and membership matter here, not free's own order
    if remaining != relative:
        raise ValueError(
            f"cells {sorted(relative ^ remaining)[:5]} (relative to ({x0}, {y0})) are outside the "
            f"{size_x} x {size_y} grid or are its start/goal corners"
        )
    return [(x + x0, y + y0) for x, y in remaining]


def paper_order(world: World) -> tuple[tuple[Cell, ...], tuple[Cell, ...]]:
    """The world's walls and pits, each in the paper's list order."""
    rank = {
        c: k
        for k, c in enumerate(
            paper_list_order(world.walls + world.pits, world.size_x, world.size_y, world.x0, world.y0)
        )
    }
    return tuple(sorted(world.walls, key=rank.__getitem__)), tuple(sorted(world.pits, key=rank.__getitem__))


def paper_tree(
    rng: random.Random, size_x: int, size_y: int, max_backtracks: int = MAX_BACKTRACKS
) -> bytearray | None:
    """Tree cells as a column-major mask (start = index 0, goal = last) found by the paper's search, or
    None when the search backtracked more than `max_backtracks` times (or, which the paper's code does not
    guard against, ran out of choices at the start).

    The search state is kept incrementally and undone on each backtrack: `touching[i]` counts the tree
    neighbours of cell i, and `front` lists the non-tree cells touching exactly one tree cell (the paper's
    `children` before its removals), with `where` its inverse. A node on the stack is a tree cell plus its
    creation time; the paper removes a backtracked cell from the choices of every node then on the stack,
    which is recorded as `removed_at[cell] = time`: a cell is forbidden at a node iff it was removed after
    that node was created (nodes created later compute fresh choices, as in the paper).
    """
    return _search(rng, size_x, size_y, max_backtracks)[0]


def _search(rng: random.Random, size_x: int, size_y: int, max_backtracks: int) -> tuple[bytearray | None, int]:
    """`paper_tree`'s search, also returning how many times it backtracked (for the measurements)."""
    n = size_x * size_y
    goal = n - 1
    neighbours = neighbour_table(size_x, size_y)
    in_tree = bytearray(n)
    touching = bytearray(n)
    front: list[int] = []
    where = [-1] * n
    removed_at = [-1] * n
    random_float = rng.random

    def front_add(i: int) -> None:
        where[i] = len(front)
        front.append(i)

    def front_remove(i: int) -> None:
        k = where[i]
        last = front.pop()
        if last != i:
            front[k] = last
            where[last] = k
        where[i] = -1

    def join(i: int) -> None:
        in_tree[i] = 1
        if where[i] >= 0:
            front_remove(i)
        for j in neighbours[i]:
            touching[j] += 1
            if not in_tree[j]:
                if touching[j] == 1:
                    front_add(j)
                elif touching[j] == 2:
                    front_remove(j)

    def leave(i: int) -> None:
        in_tree[i] = 0
        for j in neighbours[i]:
            touching[j] -= 1
            if not in_tree[j]:
                if touching[j] == 1:
                    front_add(j)
                elif touching[j] == 0:
                    front_remove(j)
        front_add(i)  # i touched exactly one tree cell when it joined, and its later neighbours are gone

    time = 0
    stack_cells = [0]
    stack_born = [0]
    join(0)
    backtracks = 0
    while True:
        cell = stack_cells[-1]
        if cell == goal:
            return in_tree, backtracks
        born = stack_born[-1]
        choices = [i for i in front if removed_at[i] <= born]
        if choices:
            i = choices[int(random_float() * len(choices))]
            time += 1
            stack_cells.append(i)
            stack_born.append(time)
            join(i)
            continue
        # Dead end: undo the last cell and forbid it at every node still on the stack.
        backtracks += 1
        if backtracks > max_backtracks or len(stack_cells) == 1:
            return None, backtracks
        stack_cells.pop()
        stack_born.pop()
        leave(cell)
        time += 1
        removed_at[cell] = time
