"""What every world generator shares: its settings (`GeneratorConfig`, checked by `check_ranges`), the
registry of generators by name (`register`, `sample_world`), the per-world RNG, and the driver that draws
distinct worlds in index order, in a process pool when asked (`generate_worlds`)."""

from __future__ import annotations

import multiprocessing
import random
import signal
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from itertools import count

from pipeline.core.checks import require
from pipeline.core.world import MOVES, World

# A generator: one world from the RNG's stream, within the config's ranges.
Sampler = Callable[[random.Random, "GeneratorConfig"], World]

# The generators by name (`GeneratorConfig.generator`), in the order they registered: the package imports
# each generator's module, and the module registers itself.
GENERATORS: dict[str, Sampler] = {}


def register(name: str) -> Callable[[Sampler], Sampler]:
    """A decorator that makes a sampler the generator named ``name``."""

    def add(sampler: Sampler) -> Sampler:
        if name in GENERATORS:
            raise ValueError(f"a generator named {name!r} is already registered")
        GENERATORS[name] = sampler
        return sampler

    return add


def check_ranges(generator: str, frame: int, p_pit: Sequence[float], sizes: dict[str, Sequence[int]]) -> None:
    """Raise `SettingError` naming the first value no generator can take: an unknown generator, a size range
    (keyed by its setting's name) that is not [min, max] with 2 <= min <= max <= frame, or a p_pit range that
    is not [min, max] within [0, 1]. `GeneratorConfig` checks its ranges with it, and the data settings their
    ranges of each split, so both refuse the same values with the same words."""
    require(generator in GENERATORS, "generator", generator, f"one of {', '.join(GENERATORS)}")
    for name, value in sizes.items():
        require(len(value) == 2, name, value, "[min, max]")
        require(2 <= value[0] <= value[1] <= frame, name, value, f"2 <= min <= max <= frame ({frame})")
    require(len(p_pit) == 2 and 0.0 <= p_pit[0] <= p_pit[1] <= 1.0, "p_pit", p_pit,
            "[min, max] with 0 <= min <= max <= 1")


@dataclass(frozen=True)
class GeneratorConfig:
    """Sampling ranges (inclusive) for the world sizes and the pit probability, inside a square frame, and
    the generator (a name in `GENERATORS`) that grows the worlds."""

    size_x: tuple[int, int] = (2, 10)
    size_y: tuple[int, int] = (2, 10)
    frame: int = 20
    p_pit: tuple[float, float] = (0.1, 0.5)
    # "project": restart the tree when the goal gets cut off (generators.project); "paper": the paper's
    # backtracking search and list order (generators.paper).
    generator: str = "project"
    # Not in the paper: the fraction of worlds whose start and goal are the two ends of the longest path of a
    # tree grown from any cell (deep maps: longer paths than corner to corner in the same sides). "project" only.
    deep: float = 0.0

    def __post_init__(self) -> None:
        check_ranges(self.generator, self.frame, self.p_pit, {"size_x": self.size_x, "size_y": self.size_y})
        check_deep(self.generator, self.deep)


def check_deep(generator: str, deep: float, name: str = "deep") -> None:
    """Raise `SettingError` (naming the setting ``name``) unless ``deep`` is a fraction in [0, 1] that the
    generator can draw (0 for "paper")."""
    require(0.0 <= deep <= 1.0, name, deep, "a fraction in [0, 1]")
    require(deep == 0.0 or generator == "project", name, deep, f"0 with generator={generator} (deep worlds are "
            "the project generator's)")


def world_rng(seed: int | str, split: str, index: int) -> random.Random:
    """The RNG of candidate `index`: it depends on nothing else, so any worker can draw it."""
    return random.Random(f"{seed}:{split}:{index}")


def sample_world(rng: random.Random, cfg: GeneratorConfig) -> World:
    """One world from the generator ``cfg`` names, all its randomness drawn from ``rng``."""
    return GENERATORS[cfg.generator](rng, cfg)


_NEIGHBOURS: dict[tuple[int, int], tuple[tuple[int, ...], ...]] = {}


def neighbour_table(size_x: int, size_y: int) -> tuple[tuple[int, ...], ...]:
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
    cfg: GeneratorConfig | None = None,
    split: str = "train",
    exclude: set | frozenset = frozenset(),
    workers: int = 1,
) -> list[World]:
    """`n` distinct worlds not in `exclude` (a set of `World.key()`), identical for any `workers`; ``cfg``:
    `GeneratorConfig()` when None.

    Candidate i depends only on (seed, split, i); candidates are filtered in index order, so the result
    is a pure function of the arguments other than `workers`.
    """
    # None, not a GeneratorConfig() default: the default would be checked when this module is imported,
    # before any generator has registered.
    cfg = GeneratorConfig() if cfg is None else cfg
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
