"""The table registry drives the report: every entry is computed, written as CSV (and Markdown), and linked
from ``report.md`` in the registry's order; a new table is one entry."""

from __future__ import annotations

import pandas as pd

from pipeline.core.variants import PAPER_ROWS, VARIANTS
from pipeline.report import build, registry
from pipeline.report.markdown import markdown_table
from pipeline.report.registry import SUCCESS_TABLES, TABLES, Table


def _links(index: str) -> list[str]:
    """The list of links under ``## Tables``."""
    return index.split("\n## Tables\n\n", 1)[1].split("\n\n", 1)[0].splitlines()


def test_every_registered_table_is_written_and_linked_in_order(built):
    result, _ = built
    folder = result.out_dir / "tables"
    assert set(result.tables) == set(TABLES)
    assert {p.name for p in folder.iterdir()} == {f"{key}.csv" for key in TABLES} | {
        f"{key}.md" for key, table in TABLES.items() if table.render is not None}
    links = []
    for key, table in TABLES.items():
        frame = pd.read_csv(folder / f"{key}.csv")
        assert list(frame.columns) == list(result.tables[key].columns) and len(frame) == len(result.tables[key])
        if table.render is None:
            links.append(f"- [{table.title}](tables/{key}.csv)")
        else:
            assert (folder / f"{key}.md").read_text().startswith(f"# {table.title}\n\n{table.note}\n")
            links.append(f"- [{table.title}](tables/{key}.md) ([csv](tables/{key}.csv))")
    assert _links((result.out_dir / "report.md").read_text()) == links


def test_a_success_table_shows_its_rows_in_order(built):
    result, _ = built
    assert [t.key for t in SUCCESS_TABLES] == ["table1", "table7", "table8", "table_named"]
    for table in SUCCESS_TABLES:
        assert set(table.rows) <= set(VARIANTS), table.key
        assert list(dict.fromkeys(result.tables[table.key]["variant"])) == list(table.rows)
        text = (result.out_dir / "tables" / f"{table.key}.md").read_text()
        shown = [line.split(" | ")[0][2:] for line in text.split("\n## all\n", 1)[1].split("\n## ", 1)[0].splitlines()
                 if line.startswith("| ")][2:]   # past the header and the rule
        assert shown == [PAPER_ROWS[v] for v in table.rows]


def test_a_new_table_is_one_entry(store, tmp_path, monkeypatch):
    per_mode = Table("episodes_per_mode", "Episodes per mode",
                     lambda data, cells: data.episodes.groupby("mode").size().rename("n").reset_index(),
                     lambda title, note, frame: f"# {title}\n\n{note}\n\n"
                     + markdown_table(list(frame.columns), frame.values.tolist()) + "\n",
                     "Every episode read, by mode.")
    monkeypatch.setitem(registry.TABLES, per_mode.key, per_mode)
    result = build.build_report(store.uri, "cogmap", tmp_path, log_run=False)
    assert (tmp_path / "tables" / "episodes_per_mode.csv").read_text() == "mode,n\noptimal,120\nreachable,200\n"
    assert "| reachable | 200 |" in (tmp_path / "tables" / "episodes_per_mode.md").read_text()
    assert _links((tmp_path / "report.md").read_text())[-1] == (
        "- [Episodes per mode](tables/episodes_per_mode.md) ([csv](tables/episodes_per_mode.csv))")
    assert tmp_path / "tables" / "episodes_per_mode.md" in result.paths
