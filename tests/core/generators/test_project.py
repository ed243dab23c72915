"""The project's generator: the layout follows the config, the free cells form a tree, and its worlds look
like the paper's released test set."""

from __future__ import annotations

import random

from conftest import free_cells_form_a_tree, worlds
from hypothesis import given

from pipeline.core.generators import GeneratorConfig, generate_worlds, sample_world, world_stats
from pipeline.core.world import World


def test_generated_layout_follows_the_config():
    cfg = GeneratorConfig(size_x=(3, 6), size_y=(2, 4), frame=8)
    for w in generate_worlds(300, seed=2, cfg=cfg):
        assert 3 <= w.size_x <= 6 and 2 <= w.size_y <= 4
        assert 0 <= w.x0 and w.x1 < 8 and 0 <= w.y0 and w.y1 < 8
        assert w.start == (w.x0, w.y0) and w.goal == (w.x1, w.y1)


def test_pits_only_and_walls_only():
    rng = random.Random(0)
    assert not sample_world(rng, GeneratorConfig(p_pit=(0.0, 0.0))).pits
    assert not sample_world(rng, GeneratorConfig(p_pit=(1.0, 1.0))).walls


@given(worlds())
def test_free_cells_form_a_tree(world):
    assert free_cells_form_a_tree(world)
    n_free = sum(world.is_free((x, y)) for x in range(world.x0, world.x1 + 1) for y in range(world.y0, world.y1 + 1))
    assert n_free + len(world.walls) + len(world.pits) == world.size_x * world.size_y


def test_generator_matches_the_paper_test_distribution(paper_worlds):
    """Same recipe as the paper: our 2..20 worlds look like its released test set on every summary."""
    ours = generate_worlds(600, seed=0, cfg=GeneratorConfig(size_x=(2, 20), size_y=(2, 20)), split="test")

    def summary(ws: list[World]) -> tuple[float, float, float]:
        cells = sum(w.size_x * w.size_y for w in ws)
        free = 1 - sum(len(w.walls) + len(w.pits) for w in ws) / cells
        pits = sum(len(w.pits) for w in ws) / sum(len(w.pits) + len(w.walls) for w in ws)
        up_right = sum(world_stats(w).up_right_only for w in ws) / len(ws)
        return free, pits, up_right

    for ours_value, paper_value, tolerance in zip(summary(ours), summary(paper_worlds), (0.02, 0.03, 0.06)):
        assert abs(ours_value - paper_value) < tolerance


def _tree_distances(world: World, origin) -> dict:
    distances, order = {origin: 0}, [origin]
    for x, y in order:
        for cell in ((x + 1, y), (x - 1, y), (x, y + 1), (x, y - 1)):
            if world.is_free(cell) and cell not in distances:
                distances[cell] = distances[(x, y)] + 1
                order.append(cell)
    return distances


def test_deep_worlds_join_the_ends_of_the_longest_free_path():
    """`deep` (not in the paper): start and goal are the two ends of the free tree's longest path, so the same
    sides hold longer paths than corner to corner; deep=0 draws the same worlds as before it existed."""
    cfg = GeneratorConfig(size_x=(2, 4), size_y=(2, 4), frame=6, deep=1.0)
    deep = generate_worlds(300, seed=1, cfg=cfg)
    for world in deep:
        assert free_cells_form_a_tree(world)
        free = list(_tree_distances(world, world.start))
        diameter = max(max(_tree_distances(world, cell).values()) for cell in free)
        assert len(world.optimal_moves()) == diameter
    corner = generate_worlds(300, seed=1, cfg=GeneratorConfig(size_x=(2, 4), size_y=(2, 4), frame=6))
    assert max(len(w.optimal_moves()) for w in corner) == 6 < max(len(w.optimal_moves()) for w in deep)
    assert any(w.start != (w.x0, w.y0) for w in deep)
    half = generate_worlds(300, seed=1, cfg=GeneratorConfig(size_x=(2, 4), size_y=(2, 4), frame=6, deep=0.5))
    assert 0 < sum(w.start != (w.x0, w.y0) or w.goal != (w.x1, w.y1) for w in half) < 300
    # deep=0 makes no draw for the choice: the stream, and so every world, is the one without the setting.
    assert corner == generate_worlds(300, seed=1, cfg=GeneratorConfig(size_x=(2, 4), size_y=(2, 4), frame=6, deep=0.0))
