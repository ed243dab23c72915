"""World generation: determinism, worker independence, dedup/exclusion, the tree property, stats."""

from __future__ import annotations

import json
import random

import pytest
from conftest import free_cells_form_a_tree, worlds
from hypothesis import given

from pipeline.core.generation import GeneratorConfig, WorldStats, generate_worlds, sample_world, world_stats
from pipeline.core.world import World


def _dump(ws: list[World]) -> str:
    return "\n".join(json.dumps(w.to_json()) for w in ws)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"size_x": (1, 10)}, "size_x=\\(1, 10\\)"),
        ({"size_y": (5, 4)}, "size_y=\\(5, 4\\)"),
        ({"size_x": (2, 21)}, "frame=20"),
        ({"size_y": (2, 12), "frame": 10}, "frame=10"),
        ({"p_pit": (-0.1, 0.5)}, "p_pit"),
        ({"p_pit": (0.5, 1.5)}, "0 <= low <= high <= 1"),
    ],
)
def test_config_validation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        GeneratorConfig(**kwargs)


def test_same_seed_same_worlds_byte_for_byte():
    assert _dump(generate_worlds(200, seed=7)) == _dump(generate_worlds(200, seed=7))
    assert _dump(generate_worlds(200, seed=7)) != _dump(generate_worlds(200, seed=8))
    assert _dump(generate_worlds(200, seed=7)) != _dump(generate_worlds(200, seed=7, split="test"))


def test_prefix_stability():
    """Asking for more worlds extends the list: candidate i never depends on n."""
    assert generate_worlds(300, seed=3)[:100] == generate_worlds(100, seed=3)


def test_workers_do_not_change_the_result():
    cfg = GeneratorConfig(size_x=(2, 12), size_y=(2, 12))
    assert _dump(generate_worlds(700, seed=1, cfg=cfg, workers=1)) == _dump(
        generate_worlds(700, seed=1, cfg=cfg, workers=2)
    )


def test_no_duplicates_even_when_the_space_is_tiny():
    # 2x2 worlds at a fixed offset: 2 trees x 2 obstacle kinds = 4 distinct worlds only.
    cfg = GeneratorConfig(size_x=(2, 2), size_y=(2, 2), frame=2)
    ws = generate_worlds(4, seed=0, cfg=cfg)
    assert len({w.key() for w in ws}) == 4


def test_exclude_is_respected():
    test = generate_worlds(300, seed=0, split="test")
    excluded = {w.key() for w in test}
    train = generate_worlds(2000, seed=0, split="train", exclude=excluded)
    assert len(train) == 2000
    assert len({w.key() for w in train}) == 2000
    assert not excluded & {w.key() for w in train}
    # And exclusion bites: worlds a plain run would return are skipped.
    plain = generate_worlds(100, seed=5)
    dropped = {w.key() for w in plain[:50]}
    again = generate_worlds(100, seed=5, exclude=dropped)
    assert again[:50] == plain[50:]


def test_bad_arguments():
    with pytest.raises(ValueError, match="workers"):
        generate_worlds(3, seed=0, workers=0)
    assert generate_worlds(0, seed=0) == []


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


def test_world_stats_example(example_world):
    assert world_stats(example_world) == WorldStats(
        size_x=4, size_y=3, optimal_length=5, dead_ends=1, up_right_only=True, interpolated=True
    )
    assert not world_stats(example_world, train_max=(3, 10)).interpolated


def _world(size_x: int, size_y: int, walls: list, goal: list) -> World:
    question = {
        "world_size_x": size_x,
        "world_size_y": size_y,
        "wall": walls,
        "pit": [],
        "start": [0, 0],
        "goal": goal,
        "gridstart_x": 0,
        "gridstart_y": 0,
    }
    return World.from_json({"question": question})


def test_world_stats_dead_end_branch():
    # Path up the left column then along the top; (2, 1)-(2, 0) hangs off the goal: one dead end.
    stats = world_stats(_world(3, 3, [[1, 0], [1, 1]], [2, 2]))
    assert stats.dead_ends == 1 and stats.optimal_length == 4 and stats.up_right_only


def test_world_stats_detour_needs_down():
    # A snake: up, up, right, right, down, down, right, right, up, up; no branches.
    stats = world_stats(_world(5, 3, [[1, 0], [1, 1], [3, 1], [3, 2]], [4, 2]))
    assert stats == WorldStats(
        size_x=5, size_y=3, optimal_length=10, dead_ends=0, up_right_only=False, interpolated=True
    )


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


def test_asking_for_more_distinct_worlds_than_exist_fails_naming_the_numbers():
    # 2 x 2 worlds in a 2 x 2 frame: two trees, each with one obstacle cell (wall or pit): 4 worlds.
    cfg = GeneratorConfig(size_x=(2, 2), size_y=(2, 2), frame=2)
    assert len(generate_worlds(4, 0, cfg)) == 4
    with pytest.raises(ValueError, match="found only 4 of n=5 distinct train worlds"):
        generate_worlds(5, 0, cfg)
