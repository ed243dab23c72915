"""Reading the store: which job runs count, shared eval runs, report runs left out."""

from __future__ import annotations

import pytest

from pipeline.report import load
from pipeline.report.registry import compute_tables
from pipeline.report.stats import wilson_interval

from .store import cell


def test_table1_uses_latest_finished_job(built):
    result, _ = built
    row = cell(result.tables["table1"], "optimal", "fwd", "marking-deadend")
    assert (row["status"], row["n"], row["successes"], row["n_seeds"]) == ("ok", 40, 30, 1)
    assert row["rate"] == pytest.approx(0.75)
    assert (row["ci_low"], row["ci_high"]) == pytest.approx(wilson_interval(30, 40))
    assert row["paper"] == pytest.approx(0.585)
    assert any("FAILED" in note for note in result.notes)
    assert any("superseded" in note for note in result.notes)


def test_reused_eval_run_serves_both_jobs(built):
    result, _ = built
    for direction in ("fwd", "bwd"):
        row = cell(result.tables["table1"], "reachable", direction, "none")
        assert (row["successes"], row["n"], row["paper"]) == (12, 40, 0.321)


def test_report_runs_are_not_read_as_jobs(built):
    result, store = built
    data = load.load_store(store.uri, "cogmap")
    assert len(data.jobs) == len(result.tables["jobs"]) == 9
    assert compute_tables(data)["table1"].equals(result.tables["table1"])
