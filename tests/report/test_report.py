"""The report, end to end on a small real MLflow store, and its statistics against known values."""

from __future__ import annotations

import json
import logging
import math
import time

import pandas as pd
import pytest
from scipy.stats import binomtest

from pipeline.core import variants
from pipeline.report import build, load, paper, tables
from pipeline.report.stats import mcnemar, mcnemar_exact, seeded_rate, wilson_interval
from pipeline.workflow.tracking import (CURVE_METRIC, EPISODES_ARTIFACT, JOB_KIND, KIND_TAG, REPORT_KIND,
                               STEP_KIND, STEP_TAG, ensure_experiment, step_run_tag)

N = 40


# ------------------------------------------------------------------------------------------- statistics


def test_wilson_closed_forms():
    z2 = 1.959963984540054 ** 2
    assert wilson_interval(0, 10) == pytest.approx((0.0, z2 / (10 + z2)))      # (0, 0.27753)
    assert wilson_interval(10, 10) == pytest.approx((10 / (10 + z2), 1.0))    # (0.72247, 1)
    assert wilson_interval(0, 10)[1] == pytest.approx(0.27753, abs=1e-5)
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_wilson_matches_scipy():
    for k, n in ((30, 40), (64, 80), (1, 7), (500, 3000)):
        ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)


def test_mcnemar_exact_known_values():
    # 2 * P(X <= 4), X ~ Bin(14, 1/2) = 2 * (1 + 14 + 91 + 364 + 1001) / 2**14
    assert mcnemar_exact(4, 10) == pytest.approx(2 * 1471 / 2 ** 14)
    assert mcnemar_exact(10, 4) == pytest.approx(mcnemar_exact(4, 10))
    assert mcnemar_exact(0, 10) == pytest.approx(2 / 2 ** 10)
    assert mcnemar_exact(0, 0) == 1.0
    test = mcnemar([True, True, False, False, True], [True, False, True, False, False])
    assert (test.both, test.only_a, test.only_b, test.neither) == (1, 2, 1, 1)
    assert test.p_value == pytest.approx(1.0)


def test_seeded_rate_means_per_seed_and_pools_interval():
    rate = seeded_rate([(30, 40), (34, 40)])
    assert rate.rate == pytest.approx(0.8)
    assert (rate.successes, rate.n, rate.n_seeds) == (64, 80, 2)
    assert (rate.ci_low, rate.ci_high) == pytest.approx(wilson_interval(64, 80))
    assert (rate.seed_min, rate.seed_max) == pytest.approx((0.75, 0.85))
    assert rate.seed_sd == pytest.approx(math.sqrt(2 * 0.05 ** 2))
    unequal = seeded_rate([(1, 2), (1, 10)])
    assert unequal.rate == pytest.approx(0.3)          # mean of 0.5 and 0.1, not 2/12
    assert seeded_rate([]).n == 0 and math.isnan(seeded_rate([]).rate)


# ------------------------------------------------------------------------------------------------ store


def world(i: int) -> dict:
    """Test world i: sizes 2..8, even worlds up/right only, train maximum 5."""
    sx, sy = 2 + i % 7, 2 + (i // 7) % 7
    return {"world_index": i, "size_x": sx, "size_y": sy, "up_right_only": i % 2 == 0,
            "interpolated": sx <= 5 and sy <= 5, "dead_ends": i % 3,
            "optimal_length": sx + sy - 2 + (0 if i % 2 == 0 else 2)}


def episodes(mode: str, wins: set[int], dfs: bool = False) -> list[dict]:
    records = []
    for i in range(N):
        w, ok = world(i), i in wins
        n = w["optimal_length"]
        if mode == "reachable":
            outcome = "success" if ok else ("deadend", "max_step", "invalid", "error")[i % 4]
            extra = {"n_moves": (n * n if dfs else n) if ok else 3, "parsed": None, "valid": None,
                     "reaches_goal": None, "map_exact": None, "map_first_error": None}
        else:
            outcome = "success" if ok else "fail"
            extra = {"n_moves": n, "parsed": True, "valid": ok or i % 2 == 0,
                     "reaches_goal": ok or i % 4 == 0, "map_exact": ok,
                     "map_first_error": None if ok else 1 + i % 5}
        records.append({**w, "success": ok, "outcome": outcome, "moves": ["up"] * extra["n_moves"],
                        "error": "prompt too long" if outcome == "error" else None, **extra})
    return records


class Store:
    """Builds runs in the layout of pipeline.workflow.tracking with the MLflow client."""

    def __init__(self, tmp_path):
        from mlflow import MlflowClient

        self.uri = f"sqlite:///{tmp_path}/mlflow.db"
        self.exp_id = ensure_experiment(self.uri, "cogmap", str(tmp_path / "artifacts"))
        self.client = MlflowClient(self.uri)
        self.tmp = tmp_path
        self.clock = int(time.time() * 1000) - 10_000_000

    def _run(self, tags: dict, parent: str | None = None) -> str:
        self.clock += 1000
        if parent:
            tags = {**tags, "mlflow.parentRunId": parent}
        return self.client.create_run(self.exp_id, start_time=self.clock, tags=tags).info.run_id

    def _history(self, run_id: str, key: str, points: list[tuple[int, float]]) -> None:
        for step, value in points:
            self.client.log_metric(run_id, key, value, step=step)

    def job(self, mode, direction, variant, seed=0, *, wins=None, status="FINISHED",
            eval_run=None, loss=None, curve=None, artifact=True, job_tags=None) -> tuple[str, str]:
        """A job run with nested finetune and eval runs (or pointing at ``eval_run``)."""
        job = self._run({KIND_TAG: JOB_KIND, "mode": mode, "direction": direction, "variant": variant,
                         "seed": str(seed), "paper_row": variants.PAPER_ROWS[variant], **(job_tags or {})})
        tags = {}
        if variant != "dfs":
            finetune = self._run({KIND_TAG: STEP_KIND, STEP_TAG: "finetune"}, job)
            self._history(finetune, "loss", loss or [(10, 2.0), (20, 1.0), (30, 0.5)])
            self.client.set_terminated(finetune)
            tags[step_run_tag("finetune")] = finetune
        if eval_run is None:
            eval_run = self._run({KIND_TAG: STEP_KIND, STEP_TAG: "eval"}, job)
            if artifact:
                folder = self.tmp / eval_run
                folder.mkdir()
                path = folder / EPISODES_ARTIFACT
                path.write_text("".join(json.dumps(e) + "\n"
                                        for e in episodes(mode, wins, variant == "dfs")))
                self.client.log_artifact(eval_run, str(path))
            if curve:
                self._history(eval_run, CURVE_METRIC, curve)
            self.client.set_terminated(eval_run)
        tags[step_run_tag("eval")] = eval_run
        for key, value in tags.items():
            self.client.set_tag(job, key, value)
        self.client.set_terminated(job, status)
        return job, eval_run


FWD_MD_WINS = set(range(30))                          # 30/40
FWD_NM_WINS = set(range(5, 25)) | {30, 31, 32, 33}     # 24/40: 20 shared, 4 only here, 10 only in md


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    s = Store(tmp_path_factory.mktemp("store"))
    s.job("optimal", "fwd", "marking-deadend", wins=set(range(5)))             # superseded below
    s.job("optimal", "fwd", "marking-deadend", wins=FWD_MD_WINS,
          curve=[(100, 0.1), (200, 0.5), (300, 0.7)])
    s.job("optimal", "fwd", "marking-deadend", wins=set(), status="FAILED")   # ignored
    s.job("optimal", "fwd", "no-marking", wins=FWD_NM_WINS)
    s.job("optimal", "bwd", "cot", wins=set(range(10)), curve=[(100, 0.05), (300, 0.2)])
    s.job("reachable", "bwd", "marking-deadend", 0, wins=set(range(30)),
          curve=[(100, 0.3), (300, 0.8)])
    s.job("reachable", "bwd", "marking-deadend", 1, wins=set(range(34)),
          curve=[(100, 0.4), (300, 0.9)])
    s.job("reachable", "bwd", "dfs", wins=set(range(36)))
    _, shared = s.job("reachable", "fwd", "none", wins=set(range(12)))
    s.job("reachable", "bwd", "none", eval_run=shared)                       # reused eval run
    s.job("reachable", "fwd", "no-all", artifact=False)                      # eval without episodes
    return s


@pytest.fixture(scope="module")
def built(store, tmp_path_factory):
    out = tmp_path_factory.mktemp("report")
    return build.build_report(store.uri, "cogmap", out), store


def cell(table, mode, direction, variant, subset="all"):
    rows = table[(table["mode"] == mode) & (table["direction"] == direction)
                 & (table["variant"] == variant) & (table["subset"] == subset)]
    assert len(rows) == 1
    return rows.iloc[0]


# ----------------------------------------------------------------------------------------------- tables


def test_table1_uses_latest_finished_job(built):
    result, _ = built
    row = cell(result.tables["table1"], "optimal", "fwd", "marking-deadend")
    assert (row["status"], row["n"], row["successes"], row["n_seeds"]) == ("ok", 40, 30, 1)
    assert row["rate"] == pytest.approx(0.75)
    assert (row["ci_low"], row["ci_high"]) == pytest.approx(wilson_interval(30, 40))
    assert row["paper"] == pytest.approx(0.585)
    assert any("FAILED" in note for note in result.notes)
    assert any("superseded" in note for note in result.notes)


def test_missing_cells_are_missing_not_zero(built):
    result, _ = built
    row = cell(result.tables["table1"], "optimal", "bwd", "marking-deadend")
    assert row["status"] == tables.MISSING and math.isnan(row["rate"]) and row["paper"] == 0.705
    eight = result.tables["table8"]
    assert (eight["status"] == tables.MISSING).all()
    no_all = cell(result.tables["table7"], "reachable", "fwd", "no-all")   # eval without episodes
    assert no_all["status"] == tables.MISSING
    assert any(EPISODES_ARTIFACT in note for note in result.notes)
    text = (result.out_dir / "tables" / "table1.md").read_text()
    assert "not run · paper 0.705" in text
    assert "0.750 [" in text and "· paper 0.585" in text


def test_two_seeds_mean_with_pooled_interval(built):
    result, _ = built
    row = cell(result.tables["table1"], "reachable", "bwd", "marking-deadend")
    assert (row["n_seeds"], row["n"], row["successes"]) == (2, 80, 64)
    assert row["rate"] == pytest.approx(0.8)
    assert (row["ci_low"], row["ci_high"]) == pytest.approx(wilson_interval(64, 80))
    assert (row["seed_min"], row["seed_max"]) == pytest.approx((0.75, 0.85))
    assert row["paper"] == pytest.approx(0.885)
    assert "{2 seeds: 0.750–0.850}" in (result.out_dir / "tables" / "table1.md").read_text()


def test_reused_eval_run_serves_both_jobs(built):
    result, _ = built
    for direction in ("fwd", "bwd"):
        row = cell(result.tables["table1"], "reachable", direction, "none")
        assert (row["successes"], row["n"], row["paper"]) == (12, 40, 0.321)


def test_subsets(built):
    result, _ = built
    table = result.tables["table1"]
    up_right = cell(table, "optimal", "fwd", "marking-deadend", "up/right only")
    assert (up_right["successes"], up_right["n"]) == (15, 20)     # even worlds below 30
    assert math.isnan(up_right["paper"])                           # the paper does not split
    interp = cell(table, "optimal", "fwd", "marking-deadend", "interpolated")
    worlds = [world(i) for i in range(N)]
    expected = sum(w["interpolated"] for w in worlds if w["world_index"] in FWD_MD_WINS)
    assert (interp["successes"], interp["n"]) == (expected, sum(w["interpolated"] for w in worlds))
    extrap = cell(table, "optimal", "fwd", "marking-deadend", "extrapolated")
    assert interp["n"] + extrap["n"] == N
    assert set(table["subset"]) == set(tables.SUBSETS)


def test_paper_numbers_match_spec():
    spec = {  # docs/spec.md §5, (mode, variant): (FWD, BWD)
        ("optimal", "none"): (0.190, 0.190), ("optimal", "cot"): (0.252, 0.265),
        ("optimal", "marking-deadend"): (0.585, 0.705), ("optimal", "no-marking"): (0.618, 0.765),
        ("reachable", "none"): (0.321, 0.321), ("reachable", "cot"): (0.339, 0.287),
        ("reachable", "marking-deadend"): (0.854, 0.885), ("reachable", "no-marking"): (0.816, 0.724),
        ("optimal", "no-all-no-backtrack"): (0.295, 0.296), ("optimal", "no-all"): (0.290, 0.277),
        ("reachable", "no-all-no-backtrack"): (0.416, 0.394), ("reachable", "no-all"): (0.345, 0.283),
        ("optimal", "no-marking-no-backtrack"): (0.528, 0.406),
        ("optimal", "no-backtrack"): (0.516, 0.423),
        ("reachable", "no-marking-no-backtrack"): (0.672, 0.739),
        ("reachable", "no-backtrack"): (0.624, 0.852), ("reachable", "dfs"): (0.945, 0.945)}
    assert paper.PAPER_SUCCESS == spec


def test_table3(built):
    result, _ = built
    t3 = result.tables["table3"]
    t3 = t3[t3["subset"] == "all"].set_index("row")
    cogmap = t3.loc["cognitive map (BWD MARKING deadend)"]
    assert cogmap["rate"] == pytest.approx(0.8) and cogmap["paper"] == pytest.approx(0.885)
    assert cogmap["moves_over_optimal"] == pytest.approx(1.0)
    dfs = t3.loc["DFS exploration (BWD run)"]
    assert (dfs["successes"], dfs["n"], dfs["paper"]) == (36, 40, 0.945)
    assert dfs["moves_over_optimal"] > 1.0


def test_mcnemar_table(built):
    result, _ = built
    table = result.tables["mcnemar"]
    row = cell(table, "optimal", "fwd", "no-marking")
    assert (row["n_pairs"], row["both"], row["only_variant"], row["only_reference"]) == (40, 20, 4, 10)
    assert row["p_value"] == pytest.approx(mcnemar_exact(4, 10))
    assert row["rate_variant"] == pytest.approx(24 / 40) and row["rate_reference"] == 0.75
    dfs = cell(table, "reachable", "bwd", "dfs")
    assert (dfs["seeds"], dfs["n_pairs"]) == ("0", 40)
    assert (dfs["only_variant"], dfs["only_reference"]) == (6, 0)


def test_graded_and_outcomes(built):
    result, _ = built
    graded = result.tables["graded_optimal"]
    row = graded[(graded["subset"] == "all") & (graded["variant"] == "marking-deadend")].iloc[0]
    assert row["rate_success"] == pytest.approx(0.75) and row["rate_map_exact"] == pytest.approx(0.75)
    assert row["rate_parsed"] == 1.0 and row["n_map_wrong"] == 10
    assert row["rate_valid"] == pytest.approx((30 + 5) / 40)       # wins, plus even worlds 30..38
    assert row["first_error_median"] == pytest.approx(3.0)          # 1 + i % 5 for i = 30..39
    outcomes = result.tables["outcomes_reachable"]
    dfs = outcomes[(outcomes["subset"] == "all") & (outcomes["variant"] == "dfs")].iloc[0]
    assert dfs["rate_success"] == pytest.approx(0.9)
    assert dfs[["rate_deadend", "rate_max_step", "rate_invalid", "rate_error"]].sum() == \
        pytest.approx(0.1)


# ---------------------------------------------------------------------------------- files and the run


def test_every_file_written_and_nonempty(built):
    result, _ = built
    for path in result.paths:
        assert path.is_file() and path.stat().st_size > 0, path
    names = {p.relative_to(result.out_dir).as_posix() for p in result.paths}
    expected = {"report.md", "tables/table1.md", "tables/table1.csv", "tables/table3.md",
                "tables/mcnemar.csv", "tables/graded_optimal.md", "tables/fig4_fits.csv",
                "figures/heatmap_optimal_fwd_success.png", "figures/heatmap_optimal_bwd_success.png",
                "figures/fig4_moves_vs_optimal.png", "figures/fig3_rapid_adaptation.png",
                *(f"figures/heatmap_reachable_bwd_{m}.png"
                  for m in ("success", "deadend", "max_step", "invalid"))}
    assert expected <= names
    assert all(p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" for p in result.paths if p.suffix == ".png")
    index = (result.out_dir / "report.md").read_text()
    assert "figures/fig4_moves_vs_optimal.png" in index and "tables/table1.md" in index


def test_report_run_holds_the_files(built):
    result, store = built
    run = store.client.get_run(result.run_id)
    assert run.data.tags[KIND_TAG] == REPORT_KIND and run.info.status == "FINISHED"
    assert "mlflow.parentRunId" not in run.data.tags
    top = {a.path for a in store.client.list_artifacts(result.run_id)}
    assert {"report.md", "tables", "figures"} <= top
    figures = {a.path for a in store.client.list_artifacts(result.run_id, "figures")}
    assert figures == {f"figures/{p.name}" for p in result.paths if p.parent.name == "figures"}


def test_report_runs_are_not_read_as_jobs(built):
    result, store = built
    data = load.load_store(store.uri, "cogmap")
    assert len(data.jobs) == len(result.tables["jobs"]) == 9
    assert tables.compute_tables(data)["table1"].equals(result.tables["table1"])


# ---------------------------------------------------------------------------------- CLI and callback


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


def test_cli_missing_store_and_experiment(tmp_path, store, capsys):
    missing = f"sqlite:///{tmp_path}/nothing.db"
    assert build.main(["--tracking-uri", missing, "--out", str(tmp_path / "r")]) == 2
    assert "nothing.db" in capsys.readouterr().err
    assert not (tmp_path / "nothing.db").exists()
    assert build.main(["--tracking-uri", store.uri, "--experiment", "nope",
                        "--out", str(tmp_path / "r")]) == 2
    assert "'nope'" in capsys.readouterr().err


def test_cli_empty_experiment(tmp_path, store):
    ensure_experiment(store.uri, "empty", str(tmp_path / "artifacts"))
    out = tmp_path / "r"
    assert build.main(["--tracking-uri", store.uri, "--experiment", "empty", "--out", str(out)]) == 0
    assert "No finished job runs" in (out / "report.md").read_text()
    table1 = (out / "tables" / "table1.csv").read_text()
    assert "not run" in table1 and "0.585" in table1


def test_callback_logs_failures_as_warnings(tmp_path, caplog):
    from hydra.utils import instantiate

    callback = instantiate({"_target_": "pipeline.report.build.ReportCallback",
                            "tracking_uri": f"sqlite:///{tmp_path}/none.db", "experiment": "cogmap",
                            "out_dir": str(tmp_path / "r")})
    with caplog.at_level(logging.WARNING, logger="pipeline.report.build"):
        callback.on_multirun_end(config=None)
    assert "Could not build the report" in caplog.text


def test_callback_builds_report(store, tmp_path):
    ensure_experiment(store.uri, "empty-too", str(tmp_path / "artifacts"))
    build.ReportCallback(store.uri, "empty-too", str(tmp_path / "r")).on_multirun_end(config=None)
    assert (tmp_path / "r" / "report.md").stat().st_size > 0
    runs = store.client.search_runs([store.client.get_experiment_by_name("empty-too").experiment_id])
    assert [r.data.tags[KIND_TAG] for r in runs] == [REPORT_KIND]


# ------------------------------------------------------------------------- first wrong lines and galleries


def _graded(world_obj, variant: str, answers: list[str]) -> list[dict]:
    from pipeline.core.episodes import optimal_episode

    stats = {"size_x": world_obj.size_x, "size_y": world_obj.size_y, "optimal_length": 4, "dead_ends": 0,
             "up_right_only": True, "interpolated": True}
    return [optimal_episode(i, world_obj, stats, text, None, "bwd", variant).to_dict() for i, text in enumerate(answers)]


def test_map_errors_count_failing_answers_by_the_kind_of_their_first_wrong_line():
    from pipeline import World
    from pipeline.core.texts import golden_answer

    grid = World(3, 3, 0, 0, ((1, 1),), ((0, 2),), (0, 0), (2, 2))
    golden = golden_answer(grid, "bwd", "marking-deadend", "optimal").split("\n")
    # Answers that go wrong and then stop (no plan: they fail).
    wrong_label = golden[:5] + ["cut"]                        # Step 1: a free cell written 'cut'
    wrong_cell = golden[:2] + ["(9, 9)"]                      # Step 1: the first neighbour's coordinate
    records = _graded(grid, "marking-deadend", ["\n".join(golden), "\n".join(wrong_label), "\n".join(wrong_label),
                                                "\n".join(wrong_cell)])
    assert records[0]["success"] and records[0]["first_wrong_line"] is None
    frame = load.episodes_frame(records).assign(mode="optimal", direction="bwd", variant="marking-deadend",
                                                   seed="0")
    table = tables.map_errors_table(tables.Cells(frame))
    rows = table[table["subset"] == "all"].set_index("category")
    assert rows.loc["label: cut for move", "n"] == 2 and rows.loc["coordinate", "n"] == 1
    assert rows.loc["label: cut for move", "share"] == pytest.approx(2 / 3)
    assert rows.loc["label: cut for move", "step 1"] == 2 and rows["later_frontier_state"].sum() == 0
    by_step = tables.map_errors_by_step_table(pd.concat([frame.assign(step=100), frame.iloc[:2].assign(step=200)]))
    at = by_step[by_step["subset"] == "all"].set_index(["step", "category"])
    assert at.loc[(100, "label: cut for move"), "n"] == 2 and at.loc[(200, "label: cut for move"), "n"] == 1
    assert at.loc[(200, "label: cut for move"), "success_rate"] == pytest.approx(0.5)


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
