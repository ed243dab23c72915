"""Random world generation as the paper does it (docs/spec.md §1), seeded per world, and world statistics."""

from __future__ import annotations

import multiprocessing
import random
import signal
from dataclasses import dataclass
from itertools import count
from collections.abc import Iterator

from pipeline.core.world import MOVES, Cell, World


# How a world's free-cell tree is grown: restart on a dead end (ours), or backtrack (the paper's).
GENERATORS = ("project", "paper")


@dataclass(frozen=True)
class GeneratorConfig:
    """Sampling ranges (inclusive) for the world sizes and the pit probability, inside a square frame."""

    size_x: tuple[int, int] = (2, 10)
    size_y: tuple[int, int] = (2, 10)
    frame: int = 20
    p_pit: tuple[float, float] = (0.1, 0.5)
    # "project": restart the tree when the goal gets cut off; "paper": the paper's backtracking search and
    # list order (pipeline.core.paper_generation).
    generator: str = "project"

    def __post_init__(self) -> None:
        if self.generator not in GENERATORS:
            raise ValueError(f"generator={self.generator!r} is not allowed: use one of {', '.join(GENERATORS)}")
        for name in ("size_x", "size_y"):
            low, high = getattr(self, name)
            if not 2 <= low <= high <= self.frame:
                raise ValueError(
                    f"{name}={(low, high)} is not allowed: need 2 <= low <= high <= frame={self.frame}"
                )
        low, high = self.p_pit
        if not 0.0 <= low <= high <= 1.0:
            raise ValueError(f"p_pit={(low, high)} is not allowed: need 0 <= low <= high <= 1")


def world_rng(seed: int | str, split: str, index: int) -> random.Random:
    """The RNG of candidate `index`: it depends on nothing else, so any worker can draw it."""
    return random.Random(f"{seed}:{split}:{index}")


def sample_world(rng: random.Random, cfg: GeneratorConfig) -> World:
    """One world: size, offset and p_pit drawn once, then a random tree grown until it holds the goal."""
    if cfg.generator == "paper":
        from pipeline.core.paper_generation import sample_world_paper  # imports this module

        return sample_world_paper(rng, cfg)
    size_x = rng.randint(*cfg.size_x)
    size_y = rng.randint(*cfg.size_y)
    x0 = rng.randint(0, cfg.frame - size_x)
    y0 = rng.randint(0, cfg.frame - size_y)
    p_pit = rng.uniform(*cfg.p_pit)
    tree = None
    while tree is None:
        # The goal gets walled in by the tree in some draws: grow again, the stream continuing.
        tree = _grow_tree(rng, size_x, size_y)
    obstacles = [i for i, in_tree in enumerate(tree) if not in_tree]
    # Shuffled like the paper's own files, whose obstacle lists are in no spatial order.
    rng.shuffle(obstacles)
    walls: list[Cell] = []
    pits: list[Cell] = []
    for i in obstacles:
        cell = (x0 + i // size_y, y0 + i % size_y)
        (pits if rng.random() < p_pit else walls).append(cell)
    return World(
        size_x=size_x,
        size_y=size_y,
        x0=x0,
        y0=y0,
        walls=tuple(walls),
        pits=tuple(pits),
        start=(x0, y0),
        goal=(x0 + size_x - 1, y0 + size_y - 1),
    )


def _grow_tree(rng: random.Random, size_x: int, size_y: int) -> bytearray | None:
    """Tree cells (column-major mask, start = index 0, goal = last) or None if the goal got cut off.

    A cell joins only while it touches exactly one tree cell, which keeps the free cells a tree and
    so the shortest path unique.
    """
    n = size_x * size_y
    goal = n - 1
    tree = bytearray(n)
    # Tree neighbours per cell. A cell is put on the frontier list when this first becomes 1, so it
    # is listed once; tree cells only ever go above 1, so they are never listed again.
    touching = bytearray(n)
    neighbours = _neighbour_table(size_x, size_y)
    random_float = rng.random
    frontier = [0]
    touching[0] = 1  # the start seeds the list as if it touched the tree once
    while frontier:
        # Uniform pick (random() is several times cheaper than randrange in this hot loop);
        # stale entries, now touching two tree cells, are dropped lazily.
        k = int(random_float() * len(frontier))
        i = frontier[k]
        frontier[k] = frontier[-1]
        frontier.pop()
        if touching[i] != 1:
            continue
        tree[i] = 1
        if i == goal:
            return tree
        for j in neighbours[i]:
            touching[j] += 1
            if touching[j] == 1:
                frontier.append(j)
        if touching[goal] > 1:
            return None
    return None


_NEIGHBOURS: dict[tuple[int, int], tuple[tuple[int, ...], ...]] = {}


def _neighbour_table(size_x: int, size_y: int) -> tuple[tuple[int, ...], ...]:
    """In-grid neighbour indices of every cell (column-major), memoised per size."""
    table = _NEIGHBOURS.get((size_x, size_y))
    if table is None:
        table = tuple(
            tuple(
                (x + dx) * size_y + y + dy
                for dx, dy in MOVES.values()
                if 0 <= x + dx < size_x and 0 <= y + dy < size_y
            )
            for x in range(size_x)
            for y in range(size_y)
        )
        _NEIGHBOURS[(size_x, size_y)] = table
    return table


def _sample_chunk(args: tuple[int | str, str, GeneratorConfig, int, int]) -> list[World]:
    seed, split, cfg, begin, end = args
    return [sample_world(world_rng(seed, split, i), cfg) for i in range(begin, end)]


def _candidates(seed: int | str, split: str, cfg: GeneratorConfig, n: int, workers: int) -> Iterator[World]:
    """Candidate worlds in index order, computed in chunks (in a process pool when workers > 1)."""
    # Workers run ahead of the filter and their last chunks are thrown away: keep chunks small.
    chunk = max(64, min(512, n // (8 * workers) + 1))
    jobs = ((seed, split, cfg, begin, begin + chunk) for begin in count(0, chunk))
    if workers == 1:
        for job in jobs:
            yield from _sample_chunk(job)
        return
    with multiprocessing.Pool(workers, initializer=_default_sigterm) as pool:
        # imap keeps index order; the pool is torn down as soon as the caller stops pulling.
        for worlds in pool.imap(_sample_chunk, jobs):
            yield from worlds


def _default_sigterm() -> None:
    # Workers are forked from a job that turns SIGTERM into KeyboardInterrupt (to unwind its MLflow runs);
    # the pool stops its workers with SIGTERM, which must end them quietly, not print a traceback each.
    signal.signal(signal.SIGTERM, signal.SIG_DFL)


def generate_worlds(
    n: int,
    seed: int | str,
    cfg: GeneratorConfig = GeneratorConfig(),
    split: str = "train",
    exclude: set | frozenset = frozenset(),
    workers: int = 1,
) -> list[World]:
    """`n` distinct worlds not in `exclude` (a set of `World.key()`), identical for any `workers`.

    Candidate i depends only on (seed, split, i); candidates are filtered in index order, so the result
    is a pure function of the arguments other than `workers`.
    """
    if n < 0 or workers < 1:
        raise ValueError(f"need n >= 0 and workers >= 1, got n={n}, workers={workers}")
    worlds: list[World] = []
    seen = set(exclude)
    if n == 0:
        return worlds
    # Small size ranges hold few distinct worlds: give up (naming the numbers) rather than loop forever.
    budget = 100 * n + 10_000
    for examined, world in enumerate(_candidates(seed, split, cfg, n, workers), 1):
        if examined > budget:
            raise ValueError(
                f"found only {len(worlds)} of n={n} distinct {split} worlds in {budget} candidates with sizes "
                f"x in {list(cfg.size_x)}, y in {list(cfg.size_y)} (frame {cfg.frame}); allowed: a smaller n "
                f"or wider size ranges"
            )
        key = world.key()
        if key in seen:
            continue
        seen.add(key)
        worlds.append(world)
        if len(worlds) == n:
            break
    return worlds


@dataclass(frozen=True)
class WorldStats:
    """What the report groups results by."""

    size_x: int
    size_y: int
    optimal_length: int
    dead_ends: int
    up_right_only: bool
    interpolated: bool


def world_stats(world: World, train_max: tuple[int, int] = (10, 10)) -> WorldStats:
    """Size, optimal length, dead-end count and the up/right-only and interpolation flags of a world."""
    moves = world.optimal_moves()
    return WorldStats(
        size_x=world.size_x,
        size_y=world.size_y,
        optimal_length=len(moves),
        dead_ends=_count_dead_ends(world),
        up_right_only=set(moves) <= {"up", "right"},
        interpolated=world.size_x <= train_max[0] and world.size_y <= train_max[1],
    )


def _count_dead_ends(world: World) -> int:
    """Leaves (one free neighbour) of the start's component, other than start and goal."""
    blocked, offsets = world.padded, world.offsets()
    ends = {world.index(world.start), world.index(world.goal)}
    seen = {world.index(world.start)}
    stack = list(seen)
    leaves = 0
    while stack:
        i = stack.pop()
        free = [i + o for o in offsets if not blocked[i + o]]
        if len(free) == 1 and i not in ends:
            leaves += 1
        for j in free:
            if j not in seen:
                seen.add(j)
                stack.append(j)
    return leaves
