"""Throughput of the pure domain core, and the wall time to build the paper's full split.

Run: `.venv/bin/python benchmarks/bench_core.py [--workers 2] [--quick]`. Prints measured figures only.
"""

from __future__ import annotations

import argparse
import multiprocessing
import resource
import time
from functools import partial

from pipeline.core.generators import GeneratorConfig, generate_worlds, world_stats
from pipeline.core.texts import conversation
from pipeline.workflow.paper_data import resolve
from pipeline.core.world import World, load_worlds

# The paper's released test worlds (pipeline.workflow.paper_data: $COGMAP_PAPER_TEST, the cache, or a fetch).
TRAIN_CFG = GeneratorConfig(size_x=(2, 10), size_y=(2, 10))
TEST_CFG = GeneratorConfig(size_x=(2, 20), size_y=(2, 20))
# The longest rendering: all moves listed, every dead end marked, plus the backtrack.
RENDER = dict(direction="bwd", variant="marking-deadend", mode="optimal", prompt="paper")  # as the paper trains


def _render(worlds: list[World]) -> int:
    """Render every world's conversation; return the characters produced (so nothing is optimised away)."""
    return sum(len(turn["value"]) for w in worlds for turn in conversation(w, **RENDER))


def _render_parallel(worlds: list[World], workers: int, chunk: int = 1000) -> int:
    chunks = [worlds[i : i + chunk] for i in range(0, len(worlds), chunk)]
    if workers == 1:
        return sum(map(_render, chunks))
    with multiprocessing.Pool(workers) as pool:
        return sum(pool.imap_unordered(_render, chunks))


def _cpu_seconds() -> float:
    """User+system CPU of this process and its finished children (wall time is noisy on a shared box)."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def _timed(label: str, fn, count: int, unit: str):
    start = time.perf_counter()
    result = fn()
    seconds = time.perf_counter() - start
    print(f"{label:<46} {seconds:7.2f} s  {count / seconds:10.0f} {unit}/s")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--quick", action="store_true", help="a tenth of the full split")
    args = parser.parse_args()
    scale = 10 if args.quick else 1
    n_train, n_test = 50_000 // scale, 3_000 // scale

    print("== single process ==")
    worlds = _timed(
        "generate 5000 train worlds (2..10)", partial(generate_worlds, 5000, 0, TRAIN_CFG), 5000, "worlds"
    )
    _timed("render 5000 train conversations (bwd marking)", partial(_render, worlds), 5000, "conv")
    tests = _timed(
        "generate 1000 test worlds (2..20)",
        partial(generate_worlds, 1000, 0, TEST_CFG, "test"),
        1000,
        "worlds",
    )
    _timed("render 1000 test conversations (bwd marking)", partial(_render, tests), 1000, "conv")
    paper = load_worlds(resolve("test").path)
    _timed("render the 3000 paper test conversations", partial(_render, paper), 3000, "conv")
    share = sum(world_stats(w).up_right_only for w in paper) / len(paper)
    print(f"paper test worlds solvable with up/right only: {share:.1%}")

    print(f"== full split: {n_train} train + {n_test} test, rendered, {args.workers} workers ==")
    start, cpu_start = time.perf_counter(), _cpu_seconds()
    test = generate_worlds(n_test, 0, TEST_CFG, "test", workers=args.workers)
    t_test = time.perf_counter()
    train = generate_worlds(
        n_train, 0, TRAIN_CFG, "train", exclude={w.key() for w in test}, workers=args.workers
    )
    t_train = time.perf_counter()
    chars = _render_parallel(train + test, args.workers)
    end = time.perf_counter()
    print(f"generate test   {t_test - start:7.2f} s")
    print(f"generate train  {t_train - t_test:7.2f} s")
    print(f"render all      {end - t_train:7.2f} s  ({chars / 1e6:.0f} M characters)")
    print(f"total           {end - start:7.2f} s wall, {_cpu_seconds() - cpu_start:.2f} s CPU")


if __name__ == "__main__":
    main()
