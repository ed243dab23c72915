"""World statistics: size, optimal length, dead ends and the up/right-only and interpolation flags."""

from __future__ import annotations

from pipeline.core.generators import WorldStats, world_stats
from pipeline.core.world import World


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
