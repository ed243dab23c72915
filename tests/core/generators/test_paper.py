"""The paper's generator (pipeline.core.generators.paper): its shape distribution against an exact enumeration of
the paper's backtracking process, its wall/pit order against the released test file, determinism, the bound."""

from __future__ import annotations

import json
import random
from collections import Counter
from fractions import Fraction

import pytest
from conftest import free_cells_form_a_tree
from scipy.stats import chi2

from pipeline.core.generators import GeneratorConfig, generate_worlds, sample_world, world_rng
from pipeline.core.generators.paper import _search, paper_list_order, paper_order, paper_tree, sample_world_paper
from pipeline.core.world import World

# ---------------------------------------------------------------------------------------------------------
# Exact shape distributions, by enumerating every random choice of each process (small grids only).
# Written from the paper's description, independently of the module: explicit per-node choice sets.


def _grid(size_x: int, size_y: int):
    cells = [(x, y) for x in range(size_x) for y in range(size_y)]

    def touching(cell, tree) -> int:
        x, y = cell
        return sum(n in tree for n in ((x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)))

    def choices(tree) -> frozenset:
        return frozenset(c for c in cells if c not in tree and touching(c, tree) == 1)

    return (size_x - 1, size_y - 1), touching, choices


def exact_paper(size_x: int, size_y: int) -> dict[frozenset, Fraction]:
    """P(free cells) under the paper's search: each node keeps its own set of choices; a node with none
    left is removed and its cell struck from the choices of every node still on the stack."""
    goal, _, choices = _grid(size_x, size_y)
    out: dict[frozenset, Fraction] = Counter()

    def explore(stack: list[tuple[tuple[int, int], frozenset]], p: Fraction) -> None:
        cell, left = stack[-1]
        if cell == goal:
            out[frozenset(c for c, _ in stack)] += p
        elif not left:
            rest = [(c, k - {cell}) for c, k in stack[:-1]]
            assert rest, "the paper's search ran out of choices at the start"
            explore(rest, p)
        else:
            tree = frozenset(c for c, _ in stack)
            for c in left:
                explore([*stack, (c, choices(tree | {c}))], p / len(left))

    explore([((0, 0), choices(frozenset({(0, 0)})))], Fraction(1))
    assert sum(out.values()) == 1
    return dict(out)


def exact_restart(size_x: int, size_y: int) -> dict[frozenset, Fraction]:
    """P(free cells) under the project's process: grow; start again once the goal touches two tree cells or
    nothing can be added (so: the growth law conditioned on success)."""
    goal, touching, choices = _grid(size_x, size_y)
    done: dict[frozenset, Fraction] = Counter()

    def grow(tree: frozenset, p: Fraction) -> None:
        if goal in tree:
            done[tree] += p
            return
        left = choices(tree)
        if left and touching(goal, tree) < 2:
            for c in left:
                grow(tree | {c}, p / len(left))

    grow(frozenset({(0, 0)}), Fraction(1))
    total = sum(done.values())
    return {t: q / total for t, q in done.items()}


def _shape(world: World) -> frozenset:
    """Free cells relative to the offset (pits and walls alike)."""
    obstacles = {(x - world.x0, y - world.y0) for x, y in world.walls + world.pits}
    return frozenset(
        (x, y) for x in range(world.size_x) for y in range(world.size_y) if (x, y) not in obstacles
    )


def _chi_square(counts: Counter, reference: dict[frozenset, Fraction]) -> float:
    assert set(counts) <= set(reference), "a shape the process cannot produce"
    n = sum(counts.values())
    return sum((counts[s] - n * float(p)) ** 2 / (n * float(p)) for s, p in reference.items())


N_SAMPLES = 20_000
# Each figure is one seeded draw, so the test is deterministic; a correct sampler exceeds this quantile for a
# given seed with probability 1e-6. Against the other process's reference the statistic is expected near
# dof + N * D, D the chi-square divergence of the two exact tables (about 0.10 at 3x3 and 3x4): ~2,000+.
P_VALUE = 1e-6


@pytest.mark.parametrize(("size_x", "size_y"), [(3, 3), (3, 4)])
def test_shape_distributions_match_their_own_process_and_differ(size_x, size_y):
    paper, restart = exact_paper(size_x, size_y), exact_restart(size_x, size_y)
    assert set(paper) == set(restart)  # the same trees are possible, at different rates
    total_variation = sum(abs(paper[s] - restart[s]) for s in paper) / 2
    assert total_variation > Fraction(1, 10)  # 0.152 at 3x3, 0.145 at 3x4
    threshold = chi2.isf(P_VALUE, len(paper) - 1)  # 56.5 at 3x3 (15 dof), 125.7 at 3x4 (59 dof)

    scores = {}
    for generator in ("project", "paper"):
        cfg = GeneratorConfig(
            size_x=(size_x, size_x), size_y=(size_y, size_y), frame=size_x + size_y, generator=generator
        )
        counts = Counter(_shape(sample_world(world_rng(11, "shapes", i), cfg)) for i in range(N_SAMPLES))
        scores[generator] = (_chi_square(counts, restart), _chi_square(counts, paper))
    (project_vs_restart, project_vs_paper), (paper_vs_restart, paper_vs_paper) = scores["project"], scores["paper"]
    assert project_vs_restart < threshold, scores
    assert paper_vs_paper < threshold, scores
    assert project_vs_paper > 10 * threshold, scores
    assert paper_vs_restart > 10 * threshold, scores


def test_a_bound_of_zero_backtracks_is_the_restart_process():
    """Abandoning every search that would backtrack keeps exactly the runs the restart process keeps."""
    paper, restart = exact_paper(3, 3), exact_restart(3, 3)
    rng = random.Random("bound-zero")
    counts: Counter = Counter()
    abandoned = 0
    while sum(counts.values()) < N_SAMPLES:
        tree = paper_tree(rng, 3, 3, max_backtracks=0)
        if tree is None:
            abandoned += 1
            continue
        counts[frozenset((i // 3, i % 3) for i in range(9) if tree[i])] += 1
    # A search succeeds without backtracking with probability 157/216 at 3x3.
    assert 0.23 < abandoned / (abandoned + N_SAMPLES) < 0.32
    threshold = chi2.isf(P_VALUE, len(restart) - 1)
    assert _chi_square(counts, restart) < threshold
    assert _chi_square(counts, paper) > 10 * threshold


# ---------------------------------------------------------------------------------------------------------
# List order.


def test_list_order_reproduces_the_paper_test_file(paper_worlds):
    assert len(paper_worlds) == 3000
    for world in paper_worlds:
        # The helper ignores the order it is given: feed it the cells reversed.
        order = paper_list_order(
            list(reversed(world.walls + world.pits)), world.size_x, world.size_y, world.x0, world.y0
        )
        walls, pits = set(world.walls), set(world.pits)
        assert tuple(c for c in order if c in walls) == world.walls, world.to_json()
        assert tuple(c for c in order if c in pits) == world.pits, world.to_json()
        assert paper_order(world) == (world.walls, world.pits)


def test_list_order_is_not_a_plain_set_and_depends_on_the_grid():
    cells = [(0, 1), (1, 1), (2, 0), (2, 2), (2, 3), (3, 3), (3, 4), (4, 7), (5, 1), (6, 4)]
    in_8x8 = paper_list_order(cells, 8, 8)
    # The same cells in a 10x10 grid: another table history, (5, 1) and (6, 4) swap.
    assert paper_list_order(cells, 10, 10) == [(0, 1), (3, 4), (1, 1), (2, 0), (6, 4), (5, 1), (2, 3), (3, 3),
                                               (2, 2), (4, 7)]
    assert in_8x8 == [(0, 1), (3, 4), (1, 1), (2, 0), (5, 1), (6, 4), (2, 3), (3, 3), (2, 2), (4, 7)]
    assert paper_list_order(cells[::-1], 8, 8) == in_8x8
    # With the offset added after ordering.
    assert paper_list_order([(x + 3, y + 5) for x, y in cells], 8, 8, 3, 5) == [(x + 3, y + 5) for x, y in in_8x8]
    # A plain set of the cells has a smaller table, hence another order.
    few = [(1, 2), (2, 1), (3, 3), (0, 4), (4, 0)]
    assert paper_list_order(few, 5, 5) == [(1, 2), (4, 0), (2, 1), (0, 4), (3, 3)] != list(set(few))
    with pytest.raises(ValueError, match="outside"):
        paper_list_order([(0, 0)], 3, 3)  # the start is never an obstacle
    with pytest.raises(ValueError, match="outside"):
        paper_list_order([(5, 1)], 3, 3, 1, 1)


def test_generated_lists_are_in_paper_order():
    cfg = GeneratorConfig(size_x=(2, 12), size_y=(2, 12), generator="paper")
    for i in range(200):
        world = sample_world(world_rng("order", "train", i), cfg)
        assert paper_order(world) == (world.walls, world.pits)


# ---------------------------------------------------------------------------------------------------------
# Determinism, the tree property, the bound, dispatch.


def _dump(worlds: list[World]) -> str:
    return "\n".join(json.dumps(w.to_json()) for w in worlds)


def test_same_seed_same_worlds_and_any_number_of_workers():
    cfg = GeneratorConfig(size_x=(2, 12), size_y=(2, 12), generator="paper")
    one = generate_worlds(300, seed=5, cfg=cfg)
    assert _dump(one) == _dump(generate_worlds(300, seed=5, cfg=cfg))
    assert _dump(one) == _dump(generate_worlds(300, seed=5, cfg=cfg, workers=2))
    assert _dump(one) != _dump(generate_worlds(300, seed=6, cfg=cfg))
    project = generate_worlds(300, seed=5, cfg=GeneratorConfig(size_x=(2, 12), size_y=(2, 12)))
    assert _dump(one) != _dump(project)


def test_worlds_are_trees_with_the_paper_layout():
    cfg = GeneratorConfig(size_x=(2, 20), size_y=(2, 20), generator="paper")
    pits = cells = 0
    for i in range(150):
        world = sample_world_paper(world_rng("tree", "test", i), cfg)
        assert world.start == (world.x0, world.y0) and world.goal == (world.x1, world.y1)
        assert world.x1 < cfg.frame and world.y1 < cfg.frame
        assert free_cells_form_a_tree(world)
        pits += len(world.pits)
        cells += len(world.pits) + len(world.walls)
    assert 0.15 < pits / cells < 0.45  # p_pit ~ U(0.1, 0.5) per world


def test_the_bound_abandons_a_search_and_a_world_still_comes_out():
    # Find a 6x6 search that backtracks more than 5 times; bounded at 5 the same draws give it up.
    for seed in range(1000):
        tree, backtracks = _search(random.Random(seed), 6, 6, 10**9)
        if backtracks > 5:
            break
    else:
        pytest.fail("no 6x6 search in 1000 backtracked more than 5 times")
    assert tree is not None
    assert _search(random.Random(seed), 6, 6, 5) == (None, 6)
    assert _search(random.Random(seed), 6, 6, backtracks) == (tree, backtracks)
    # Bounded at zero, every search that meets a dead end is abandoned, yet each call returns a valid world.
    cfg = GeneratorConfig(size_x=(2, 10), size_y=(2, 10), generator="paper")
    for i in range(100):
        assert free_cells_form_a_tree(sample_world_paper(world_rng("tiny", "train", i), cfg, max_backtracks=0))
    with pytest.raises(ValueError, match="max_backtracks"):
        sample_world_paper(random.Random(0), cfg, max_backtracks=-1)


def test_generator_choice_is_validated():
    with pytest.raises(ValueError, match="generator='pape'"):
        GeneratorConfig(generator="pape")
