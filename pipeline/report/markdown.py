"""The report's tables as Markdown: cells with their intervals and the paper's number. Every renderer takes
(title, note, long table), so a registry entry (:mod:`pipeline.report.registry`) names one."""

from __future__ import annotations

import math

import pandas as pd

from pipeline.core.variants import PAPER_ROWS
from pipeline.report.tables import MISSING

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


def render_success(title: str, note: str, table: pd.DataFrame) -> str:
    """Tables 1/7/8 as Markdown: one section per subset, variants by (mode, direction)."""
    parts = [f"# {title}", "", note]
    columns = list(dict.fromkeys(zip(table["mode"], table["direction"])))
    for subset, block in table.groupby("subset", sort=False):
        rows = []
        for variant, by_variant in block.groupby("variant", sort=False):
            cells = {(r["mode"], r["direction"]): format_rate(r) for _, r in by_variant.iterrows()}
            rows.append([PAPER_ROWS.get(variant, variant), *(cells[c] for c in columns)])
        parts += ["", f"## {subset}", "",
                  markdown_table(["", *(_column_name(*c) for c in columns)], rows)]
    return "\n".join(parts) + "\n"


def render_table3(title: str, note: str, table: pd.DataFrame) -> str:
    """Table 3 as Markdown: rows by subset, plus moves over optimal length on successful episodes."""
    subsets = list(dict.fromkeys(table["subset"]))
    rows = []
    for label, block in table.groupby("row", sort=False):
        by_subset = {r["subset"]: r for _, r in block.iterrows()}
        rows.append([label, *(format_rate(by_subset[s]) for s in subsets),
                     _num(by_subset["all"]["moves_over_optimal"], 2)])
    return "\n".join([f"# {title}", "", note, "", markdown_table(["", *subsets, "moves / optimal"], rows)]) + "\n"


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
