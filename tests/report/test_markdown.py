"""The report's tables as Markdown: a cell's text, the table syntax, and each layout on the synthetic store."""

from __future__ import annotations

import math

from pipeline.report.markdown import format_rate, markdown_table, render_rows, render_success, render_table3
from pipeline.report.tables import MISSING, SUBSETS


def test_a_cell_shows_its_rate_interval_seeds_and_the_papers_number():
    one = {"status": "ok", "n": 40, "rate": 0.75, "ci_low": 0.598, "ci_high": 0.858, "n_seeds": 1, "paper": 0.585}
    assert format_rate(one) == "0.750 [0.598, 0.858] n=40 · paper 0.585"
    assert format_rate(one, with_paper=False) == "0.750 [0.598, 0.858] n=40"
    two = {**one, "n": 80, "n_seeds": 2, "seed_min": 0.7, "seed_max": 0.8, "paper": math.nan}
    assert format_rate(two) == "0.750 [0.598, 0.858] n=80 {2 seeds: 0.700–0.800}"
    assert format_rate({"status": MISSING, "n": 0, "paper": 0.705}) == "not run · paper 0.705"
    assert format_rate({"status": "n=0", "n": 0}) == "n=0"


def test_a_pipe_in_a_cell_is_escaped():
    assert markdown_table(["a", "b"], [["x|y", 1]]) == "| a | b |\n| --- | --- |\n| x\\|y | 1 |"


def test_a_success_table_has_a_section_per_subset_and_a_column_per_mode_and_direction(built):
    result, _ = built
    text = render_success("Title", "Note.", result.tables["table1"])
    assert text.startswith("# Title\n\nNote.\n\n## all\n\n"
                           "|  | Optimal FWD | Optimal BWD | Reachable FWD | Reachable BWD |\n")
    assert [line[3:] for line in text.splitlines() if line.startswith("## ")] == list(SUBSETS)
    assert ("| MARKING deadend | 0.750 [0.598, 0.858] n=40 · paper 0.585 | not run · paper 0.705 "
            "| not run · paper 0.854 | 0.800 [0.700, 0.873] n=80 {2 seeds: 0.750–0.850} · paper 0.885 |") in text


def test_table3_has_a_column_per_subset_and_moves_over_optimal(built):
    result, _ = built
    text = render_table3("Title", "Note.", result.tables["table3"])
    assert text.startswith("# Title\n\nNote.\n\n|  | all | up/right only | needs down/left | interpolated | "
                           "extrapolated | moves / optimal |\n")
    dfs = next(line for line in text.splitlines() if line.startswith("| DFS exploration (BWD run) |"))
    assert "| 0.900 [0.769, 0.960] n=40 · paper 0.945 |" in dfs and dfs.endswith("| 8.00 |")


def test_a_long_table_rounds_per_column_and_says_when_nothing_ran(built):
    result, _ = built
    text = render_rows("Title", "Note.", result.tables["mcnemar"], {"rate_variant": 3, "p_value": 4})
    assert "| optimal | FWD | no-marking | marking-deadend | 0 | 40 | 0.600 | 0.75 | 4 | 10 | 20 | 6 | 0.1796 |" in text
    empty = render_rows("Title", "Note.", result.tables["map_errors_by_step"], {})
    assert empty == "# Title\n\nNote.\n\nNo job for this table has run.\n"
