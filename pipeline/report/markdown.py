"""The report's tables as Markdown (and CSV): cells with their intervals and the paper's number."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from pipeline.core.variants import PAPER_ROWS
from pipeline.report.tables import MISSING, REACHABLE_OUTCOMES, SUCCESS_TABLES

SEED_FOOTNOTE = (
    "Cells: our success rate, its 95% Wilson interval in brackets, the paper's number (docs/spec.md §5) after "
    "'paper'. With several seeds the rate is the mean of the per-seed rates, the interval the Wilson "
    "interval of all episodes pooled over seeds (it ignores seed-to-seed variance), and the per-seed "
    "range follows in braces. Episodes that could not run count as failures. 'not run' = no finished "
    "job for that cell (never read as 0); 'n=0' = the job ran but has no episode in this subset.")


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    """A GitHub-flavoured Markdown table (``|`` in cells escaped)."""
    def line(cells: list[str]) -> str:
        return "| " + " | ".join(str(c).replace("|", "\\|") for c in cells) + " |"
    return "\n".join([line(header), line(["---"] * len(header)), *(line(r) for r in rows)])


def _num(value: float, digits: int = 3) -> str:
    return "—" if value is None or (isinstance(value, float) and math.isnan(value)) \
        else f"{value:.{digits}f}"


def format_rate(row: pd.Series | dict, with_paper: bool = True) -> str:
    """One cell: ``0.750 [0.598, 0.858] n=40 {2 seeds: 0.70–0.80} · paper 0.585``, or ``not run``."""
    if row["status"] == MISSING:
        text = MISSING
    elif row["n"] == 0:
        text = "n=0"
    else:
        text = f"{row['rate']:.3f} [{row['ci_low']:.3f}, {row['ci_high']:.3f}] n={row['n']}"
        if row["n_seeds"] > 1:
            text += f" {{{row['n_seeds']} seeds: {row['seed_min']:.3f}–{row['seed_max']:.3f}}}"
    paper = row.get("paper", math.nan)
    if with_paper and not math.isnan(paper):
        text += f" · paper {paper:.3f}"
    return text


def _column_name(mode: str, direction: str) -> str:
    return f"{mode.capitalize()} {direction.upper()}"


def render_success(title: str, table: pd.DataFrame) -> str:
    """Tables 1/7/8 as Markdown: one section per subset, variants by (mode, direction)."""
    parts = [f"# {title}", "", SEED_FOOTNOTE]
    columns = list(dict.fromkeys(zip(table["mode"], table["direction"])))
    for subset, block in table.groupby("subset", sort=False):
        rows = []
        for variant, by_variant in block.groupby("variant", sort=False):
            cells = {(r["mode"], r["direction"]): format_rate(r) for _, r in by_variant.iterrows()}
            rows.append([PAPER_ROWS.get(variant, variant), *(cells[c] for c in columns)])
        parts += ["", f"## {subset}", "",
                  markdown_table(["", *(_column_name(*c) for c in columns)], rows)]
    return "\n".join(parts) + "\n"


def render_table3(table: pd.DataFrame) -> str:
    """Table 3 as Markdown: rows by subset, plus moves over optimal length on successful episodes."""
    subsets = list(dict.fromkeys(table["subset"]))
    rows = []
    for label, block in table.groupby("row", sort=False):
        by_subset = {r["subset"]: r for _, r in block.iterrows()}
        rows.append([label, *(format_rate(by_subset[s]) for s in subsets),
                     _num(by_subset["all"]["moves_over_optimal"], 2)])
    return "\n".join([
        "# Table 3: reachable setting, cognitive map vs DFS exploration", "", SEED_FOOTNOTE,
        "The last column is the mean of moves taken / optimal length over successful episodes.", "",
        markdown_table(["", *subsets, "moves / optimal"], rows)]) + "\n"


def render_rows(title: str, note: str, table: pd.DataFrame, digits: dict[str, int]) -> str:
    """A long table as Markdown, one section per subset, floats rounded per ``digits``."""
    parts = [f"# {title}", "", note]
    columns = [c for c in table.columns if c != "subset"]
    for subset, block in table.groupby("subset", sort=False):
        rows = [[_num(r[c], digits[c]) if c in digits else
                 (r[c].upper() if c == "direction" else r[c]) for c in columns]
                for _, r in block.iterrows()]
        parts += ["", f"## {subset}", "", markdown_table(columns, rows)]
    if table.empty:
        parts += ["", "No job for this table has run."]
    return "\n".join(parts) + "\n"


MCNEMAR_NOTE = (
    "Each variant against marking-deadend of the same direction and mode, on the test worlds both were "
    "evaluated on (paired by seed and world index; with no seed in common, the lowest seed of each). "
    "only_variant / only_reference: worlds solved by one and not the other. p_value: two-sided exact "
    "McNemar test (binomial test of the discordant pairs at 1/2).")
GRADED_NOTE = (
    "Optimal setting, graded (docs/spec.md §4): the share of episodes whose plan parsed, stayed valid (never left "
    "the grid or hit an obstacle), reached the goal, was optimal (success), and whose map was exact; "
    "rates are means over seeds. first_error_*: quartiles, over wrong maps, of the first line (0-based, "
    "in the whole answer) where the answer departs from the golden one.")
MAP_ERRORS_NOTE = (
    "Failing optimal-setting episodes by the first line where the answer departs from the golden one: a "
    "section or step header, a state name (named maps), a neighbour's coordinate, its label (a move written "
    "for 'cut', 'cut' for a move, or the wrong move), a Backtrack or Plan line, or 'end' (the answer ran on "
    "past the golden one). n: episodes (all seeds); share: of the cell's failing episodes; the step columns "
    "count the thought lines by BFS step; later_frontier_state: lines of a state that was not the first "
    "one expanded in its step.")
MAP_ERRORS_BY_STEP_NOTE = (
    "The same classification for the checkpoints of jobs run with eval.curve=true (each checkpoint decoded on "
    "the first eval.curve_worlds test worlds): n_episodes and success_rate of the checkpoint, then its failing "
    "episodes by category.")
OUTCOMES_NOTE = (
    "Reachable setting: the share of each outcome (means over seeds); moves_over_optimal = mean of moves "
    "taken / optimal length over successful episodes.")


def write_tables(tables: dict[str, pd.DataFrame], out: Path) -> list[Path]:
    """Each table as CSV (long form) and Markdown; returns the paths written."""
    out.mkdir(parents=True, exist_ok=True)
    rate_digits = {c: 3 for c in ("rate_variant", "rate_reference", "rate_parsed", "rate_valid",
                                  "rate_reaches_goal", "rate_success", "rate_map_exact",
                                  *(f"rate_{o}" for o in REACHABLE_OUTCOMES))}
    rate_digits |= {"p_value": 4, "moves_over_optimal": 2, "first_error_q1": 1,
                    "first_error_median": 1, "first_error_q3": 1}
    markdown = {key: render_success(title, tables[key]) for key, (title, _) in SUCCESS_TABLES.items()}
    markdown["table3"] = render_table3(tables["table3"])
    markdown["mcnemar"] = render_rows("Paired tests against marking-deadend", MCNEMAR_NOTE,
                                      tables["mcnemar"], rate_digits)
    markdown["graded_optimal"] = render_rows("Optimal setting, graded", GRADED_NOTE,
                                             tables["graded_optimal"], rate_digits)
    markdown["outcomes_reachable"] = render_rows("Reachable setting, outcomes", OUTCOMES_NOTE,
                                                 tables["outcomes_reachable"], rate_digits)
    markdown["map_errors"] = render_rows("Optimal setting: where failing answers first go wrong",
                                         MAP_ERRORS_NOTE, tables["map_errors"], {"share": 3})
    markdown["map_errors_by_step"] = render_rows(
        "Optimal setting: where failing answers first go wrong, by training step", MAP_ERRORS_BY_STEP_NOTE,
        tables["map_errors_by_step"], {"share": 3, "success_rate": 3})
    paths = []
    for key, frame in tables.items():
        csv = out / f"{key}.csv"
        frame.to_csv(csv, index=False)
        paths.append(csv)
        if key in markdown:
            md = out / f"{key}.md"
            md.write_text(markdown[key], encoding="utf-8")
            paths.append(md)
    return paths
