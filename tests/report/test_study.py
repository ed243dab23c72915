"""The lever study table (`python -m pipeline.report.study`)."""

from __future__ import annotations

import pytest

from pipeline.report.load import ReportError
from pipeline.report.study import Row, _flat, study_table


def _records(successes: list[bool], interpolated: list[bool]) -> list[dict]:
    return [{"world_index": i, "success": s, "interpolated": p} for i, (s, p) in enumerate(zip(successes, interpolated))]


INTERP = [True, True, False, False, False, False]


def test_rows_are_rated_per_split_and_subset_and_paired_against_the_reference():
    base = Row("a", {"model.positions": "rope"}, {"valid": _records([1, 0, 0, 0, 0, 0], INTERP),
                                                   "test": _records([1, 1, 0, 0, 0, 1], INTERP)})
    lever = Row("b", {"model.positions": "nope"}, {"valid": _records([1, 1, 1, 1, 0, 0], INTERP),
                                                    "test": _records([0, 1, 1, 1, 1, 0], INTERP)})
    table = study_table([base, lever]).splitlines()
    assert table[0].startswith("| # | recipe | valid all | valid interp | valid extrap | test all")
    row = [cell.strip() for cell in table[3].split("|")[1:-1]]
    assert row[:2] == ["1", "model.positions=nope"]
    assert row[2].startswith("0.667 [") and row[2].endswith("(4/6)")        # valid all
    assert row[4].startswith("0.500 [") and row[4].endswith("(2/4)")        # valid extrapolated
    assert row[7].endswith("(3/4)")                                          # test extrapolated
    assert row[8] == "+2 / -0, p 0.5" and row[9] == "+3 / -1, p 0.62"       # McNemar on the extrapolated worlds
    assert [c.strip() for c in table[2].split("|")[1:-1]][8:] == ["-", "-"]  # the reference against itself
    with pytest.raises(ReportError, match="--reference 2: allowed 0..1"):
        study_table([base, lever], reference=2)


def test_a_job_without_validation_shows_a_dash_and_configs_flatten_to_dotted_keys():
    row = Row("a", {}, {"valid": [], "test": _records([True], [True])})
    line = study_table([row]).splitlines()[2]
    assert "(one recipe)" in line and "| - |" in line
    assert _flat({"model": {"positions": "nope", "sizes": [2, 4]}, "seed": 1}) == {
        "model.positions": "nope", "model.sizes": "[2, 4]", "seed": 1}
