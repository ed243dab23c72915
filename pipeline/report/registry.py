"""THE list of the report's tables: each declared once, with its file name, title, note, how it is computed
from the store, how it is shown in Markdown and, for a success table, its rows. The CSVs, the Markdown files
and the links in ``report.md`` all iterate over :data:`TABLES`, so a new table is one entry here.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Callable

import pandas as pd

from pipeline.core.variants import NAMED_SUFFIX, REFERENCE
from pipeline.report.load import StoreData
from pipeline.report.markdown import SEED_FOOTNOTE, render_rows, render_success, render_table3
from pipeline.report.tables import (
    REACHABLE_OUTCOMES, Cells, graded_table, jobs_table, map_errors_by_step_table, map_errors_table, mcnemar_table,
    outcomes_table, success_table, table3,
)

Compute = Callable[[StoreData, Cells], pd.DataFrame]
Render = Callable[[str, str, pd.DataFrame], str]   # (title, note, long table) -> Markdown


@dataclass(frozen=True)
class Table:
    """One table of the report: ``tables/<key>.csv`` (long form) and, if it has a renderer, ``<key>.md``."""

    key: str
    title: str
    compute: Compute | None          # None: computed where its figure is drawn (build.write_figures)
    render: Render | None = None     # None: CSV only
    note: str = ""
    rows: tuple[str, ...] = ()       # a success table's variants, in the order shown

    def markdown(self, frame: pd.DataFrame) -> str:
        """The table as Markdown, under its title and note (only for a table with a renderer)."""
        return self.render(self.title, self.note, frame)


def _success(key: str, title: str, rows: tuple[str, ...]) -> Table:
    """A success table: the rate of each of ``rows`` (variants) by mode x direction, beside the paper's."""
    return Table(key, title, lambda data, cells: success_table(cells, rows), render_success, SEED_FOOTNOTE, rows)


_RATE_DIGITS = {
    **{c: 3 for c in ("rate_variant", "rate_reference", "rate_parsed", "rate_valid", "rate_reaches_goal",
                      "rate_success", "rate_map_exact", *(f"rate_{o}" for o in REACHABLE_OUTCOMES))},
    "p_value": 4, "moves_over_optimal": 2, "first_error_q1": 1, "first_error_median": 1, "first_error_q3": 1,
}

TABLES: dict[str, Table] = {t.key: t for t in (
    _success("table1", "Table 1: success rate, baselines and the cognitive map",
             ("none", "cot", "marking-deadend", "no-marking")),
    _success("table7", "Table 7: success rate without ALL (only new neighbours listed)",
             ("no-all-no-backtrack", "no-all")),
    _success("table8", "Table 8: success rate without BACKTRACK", ("no-marking-no-backtrack", "no-backtrack")),
    _success("table_named", "Beyond the paper: each expanded state named (`From (x, y):` before its neighbours)",
             ("marking-deadend", "marking-deadend" + NAMED_SUFFIX, "no-marking", "no-marking" + NAMED_SUFFIX)),
    Table("table3", "Table 3: reachable setting, cognitive map vs DFS exploration",
          lambda data, cells: table3(cells), render_table3,
          SEED_FOOTNOTE + "\nThe last column is the mean of moves taken / optimal length over successful episodes."),
    Table("mcnemar", f"Paired tests against {REFERENCE}", lambda data, cells: mcnemar_table(cells),
          partial(render_rows, digits=_RATE_DIGITS),
          f"Each variant against {REFERENCE} of the same direction and mode, on the test worlds both were "
          "evaluated on (paired by seed and world index; with no seed in common, the lowest seed of each). "
          "only_variant / only_reference: worlds solved by one and not the other. p_value: two-sided exact "
          "McNemar test (binomial test of the discordant pairs at 1/2)."),
    Table("graded_optimal", "Optimal setting, graded", lambda data, cells: graded_table(cells),
          partial(render_rows, digits=_RATE_DIGITS),
          "Optimal setting, graded (docs/spec.md §4): the share of episodes whose plan parsed, stayed valid (never "
          "left the grid or hit an obstacle), reached the goal, was optimal (success), and whose map was exact; "
          "rates are means over seeds. first_error_*: quartiles, over wrong maps, of the first line (0-based, "
          "in the whole answer) where the answer departs from the golden one."),
    Table("outcomes_reachable", "Reachable setting, outcomes", lambda data, cells: outcomes_table(cells),
          partial(render_rows, digits=_RATE_DIGITS),
          "Reachable setting: the share of each outcome (means over seeds); moves_over_optimal = mean of moves "
          "taken / optimal length over successful episodes."),
    Table("map_errors", "Optimal setting: where failing answers first go wrong",
          lambda data, cells: map_errors_table(cells), partial(render_rows, digits={"share": 3}),
          "Failing optimal-setting episodes by the first line where the answer departs from the golden one: a "
          "section or step header, a state name (named maps), a neighbour's coordinate, its label (a move written "
          "for 'cut', 'cut' for a move, or the wrong move), a Backtrack or Plan line, or 'end' (the answer ran on "
          "past the golden one). n: episodes (all seeds); share: of the cell's failing episodes; the step columns "
          "count the thought lines by BFS step; later_frontier_state: lines of a state that was not the first "
          "one expanded in its step."),
    Table("map_errors_by_step", "Optimal setting: where failing answers first go wrong, by training step",
          lambda data, cells: map_errors_by_step_table(data.curve_episodes),
          partial(render_rows, digits={"share": 3, "success_rate": 3}),
          "The same classification for the checkpoints of jobs run with eval.curve=true (each checkpoint decoded "
          "on the first eval.curve_worlds test worlds): n_episodes and success_rate of the checkpoint, then its "
          "failing episodes by category."),
    Table("fig4_fits", "Figure 4: least-squares fits of moves taken against optimal length", None),
    Table("jobs", "Job runs used", lambda data, cells: jobs_table(data.jobs)),
)}

# The success tables (those with rows): the report's index also shows their 'all' section inline.
SUCCESS_TABLES: tuple[Table, ...] = tuple(t for t in TABLES.values() if t.rows)


def compute_tables(data: StoreData) -> dict[str, pd.DataFrame]:
    """Every table computed from the store alone, in long form (those drawn with a figure are left to it)."""
    cells = Cells(data.episodes)
    return {t.key: t.compute(data, cells) for t in TABLES.values() if t.compute is not None}


def write_tables(tables: dict[str, pd.DataFrame], out: Path) -> list[Path]:
    """Each registered table as CSV (long form) and, where it has a renderer, Markdown; the paths written.

    ``tables`` must hold every registered table (:func:`compute_tables` and the figures' tables).
    """
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for table in TABLES.values():
        frame = tables[table.key]
        csv = out / f"{table.key}.csv"
        frame.to_csv(csv, index=False)
        paths.append(csv)
        if table.render is not None:
            md = out / f"{table.key}.md"
            md.write_text(table.markdown(frame), encoding="utf-8")
            paths.append(md)
    return paths
