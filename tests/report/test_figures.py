"""The figures' inputs: the training box of a heatmap, and the episode galleries."""

from __future__ import annotations

from pipeline.report import load

from .store import Store


def test_train_box_comes_from_job_tags(tmp_path):
    from pipeline.report.figures import train_box

    s = Store(tmp_path)
    s.job("optimal", "fwd", "marking-deadend", wins=set(range(5)), job_tags={"train_max_x": "6", "train_max_y": "4"})
    s.job("optimal", "bwd", "marking-deadend", wins=set(range(5)))          # a job logged before the tags
    data = load.load_store(s.uri, "cogmap")
    by_direction = dict(tuple(data.episodes.groupby("direction")))
    # The tags win over the episodes' interpolated flags, which would infer (5, 5) here.
    assert train_box(by_direction["fwd"]) == (6, 4)
    assert train_box(by_direction["bwd"]) == (5, 5)
    # Jobs with different boxes pooled in one panel: no single tag box, so it is inferred.
    assert train_box(data.episodes) == (5, 5)


def test_a_gallery_draws_successes_above_failures_chosen_by_world_index(tmp_path):
    from pipeline import World
    from pipeline.report.figures import episode_gallery, gallery_picks

    grid = World(3, 3, 0, 0, ((1, 1),), ((0, 2),), (0, 0), (2, 2))
    records = [{"world_index": i, "success": i % 3 == 0, "outcome": "success" if i % 3 == 0 else "fail",
                "moves": [] if i == 1 else ["right", "right", "up", "up"]} for i in range(12)]
    picks = gallery_picks(list(reversed(records)))
    assert [r["world_index"] for r in picks] == [0, 3, 6, 2, 4, 5]   # a failure that never moved goes last
    path = episode_gallery([(grid, r) for r in picks], "MARKING deadend (BWD, optimal)", tmp_path / "g.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert episode_gallery([], "empty", tmp_path / "none.png") is None and not (tmp_path / "none.png").exists()
