"""The report end to end: the files, the index ``report.md``, the report run, the command line, the callback."""

from __future__ import annotations

import logging
import re

from pipeline.report import build
from pipeline.workflow.tracking import KIND_TAG, REPORT_KIND, ensure_experiment


def _section(text: str, heading: str) -> str:
    """The lines under ``heading`` up to the next heading of any level."""
    return text.split(f"\n{heading}\n", 1)[1].split("\n#", 1)[0]


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


def test_the_index_says_what_it_read_shows_the_headline_tables_and_links_what_was_written(built):
    result, store = built
    index = (result.out_dir / "report.md").read_text()
    assert index.startswith(f"# Report: experiment `cogmap`\n\nStore: `{store.uri}`. Finished job runs used: 9 "
                            "(8 with episodes, 320 episodes).\n")
    assert all(f"- {note}" in index for note in result.notes)
    table1 = _section(index, "### Table 1: success rate, baselines and the cognitive map (all test worlds)")
    assert "| MARKING deadend | 0.750 [0.598, 0.858] n=40 · paper 0.585 | not run · paper 0.705 |" in table1
    assert "| NONE | not run · paper 0.190 | not run · paper 0.190 | 0.300 [0.181, 0.454] n=40 · paper 0.321 |" \
        in table1
    table3 = _section(index, "### Table 3 (reachable)")
    assert "| DFS exploration (BWD run) | 0.900 [0.769, 0.960] n=40 · paper 0.945 |" in table3
    figures = [p for p in result.paths if p.suffix == ".png"]
    assert figures and all(f"### {p.stem}\n\n![{p.stem}](figures/{p.name})" in index for p in figures)
    written = {p.relative_to(result.out_dir).as_posix() for p in result.paths}
    assert set(re.findall(r"\]\(([^)]+)\)", index)) <= written


def test_report_run_holds_the_files(built):
    result, store = built
    run = store.client.get_run(result.run_id)
    assert run.data.tags[KIND_TAG] == REPORT_KIND and run.info.status == "FINISHED"
    assert "mlflow.parentRunId" not in run.data.tags
    top = {a.path for a in store.client.list_artifacts(result.run_id)}
    assert {"report.md", "tables", "figures"} <= top
    figures = {a.path for a in store.client.list_artifacts(result.run_id, "figures")}
    assert figures == {f"figures/{p.name}" for p in result.paths if p.parent.name == "figures"}


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
