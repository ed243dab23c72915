"""The report's tables in long form, on the synthetic store (known rates, missing cells, subsets, paired
tests, graded and outcome tables) and on graded episodes (where failing answers first go wrong)."""

from __future__ import annotations

import math

import pandas as pd
import pytest

from pipeline.report import load, tables
from pipeline.report.stats import mcnemar_exact, wilson_interval
from pipeline.workflow.tracking import EPISODES_ARTIFACT

from .store import FWD_MD_WINS, N, cell, world


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
