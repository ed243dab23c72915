"""The scored episode: its fields are the episodes.jsonl schema, it holds the world's WorldStats (written flat),
and the metrics come from records alone."""

from __future__ import annotations

from dataclasses import asdict

from pipeline.core.episodes import (EPISODE_FIELDS, EVAL_METRICS, STAT_FIELDS, metrics, optimal_episode,
                                    reachable_episode)
from pipeline.core.generators import world_stats
from pipeline.core.texts import golden_answer


def test_a_record_carries_the_worlds_statistics_right_after_its_index(example_world):
    assert EPISODE_FIELDS[1:1 + len(STAT_FIELDS)] == STAT_FIELDS
    stats = asdict(world_stats(example_world))
    episode = optimal_episode(0, example_world, stats, "", None, "fwd", "none")
    assert episode.stats == world_stats(example_world)
    record = episode.to_dict()
    assert tuple(record) == EPISODE_FIELDS and {k: record[k] for k in STAT_FIELDS} == stats


def test_metrics_count_successes_by_split_and_outcomes(example_world):
    stats = asdict(world_stats(example_world))
    golden = golden_answer(example_world, "bwd", "marking-deadend", "optimal")
    records = [optimal_episode(0, example_world, stats, golden, None, "bwd", "marking-deadend").to_dict(),
               optimal_episode(1, example_world, stats, "Plan:\nup", None, "bwd", "marking-deadend").to_dict(),
               reachable_episode(2, {**stats, "interpolated": False}, "deadend", ["down"], None).to_dict()]
    values = metrics(records)
    assert values["n_episodes"] == 3 and values["success_rate"] == 1 / 3
    assert values["success_rate_interp"] == 1 / 2 and values["success_rate_extrap"] == 0.0
    assert values["rate_deadend"] == 1 / 3 and values["rate_map_exact"] == 1 / 2
    # Records with every subset non-empty (interpolated and not, graded) get every metric.
    assert tuple(values) == EVAL_METRICS
