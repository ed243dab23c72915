"""The report: the paper's tables and figures, from the MLflow store only.

``python -m pipeline.report`` (and :class:`ReportCallback` at the end of every multirun) reads the finished
job runs of an experiment (layout in :mod:`pipeline.workflow.tracking`), their eval runs' ``episodes.jsonl`` and
metric histories, and writes the tables of :mod:`pipeline.report.registry` (CSV and Markdown), PNG figures and
an index ``report.md`` under ``out_dir``; the same files are logged as artifacts of a new run tagged
``cogmap.kind=report``.

Every rate is over episodes; an episode that could not run (``outcome == "error"``) counts as a failure.
Several seeds in one cell: the rate is the mean of the per-seed rates, the interval the 95% Wilson interval
of all episodes pooled over seeds, and the per-seed range is printed beside it.
"""

from __future__ import annotations

import argparse
import atexit
import logging
import sys
from dataclasses import dataclass
from pathlib import Path

import pandas as pd
from hydra.experimental.callback import Callback

from pipeline.core.variants import MAP_VARIANTS, REFERENCE
from pipeline.report.load import ReportError, StoreData, load_store, open_experiment
from pipeline.report.markdown import SEED_FOOTNOTE
from pipeline.report.registry import SUCCESS_TABLES, TABLES, compute_tables, write_tables
from pipeline.report.tables import Cells, rate_stats
from pipeline.report.cli import add_store_arguments, store_of
from pipeline.workflow.tracking import KIND_TAG, REPORT_KIND

log = logging.getLogger(__name__)


@dataclass
class ReportResult:
    """What :func:`build_report` wrote: every path, the tables (long form), the report run's id."""

    out_dir: Path
    paths: list[Path]
    tables: dict[str, pd.DataFrame]
    run_id: str | None
    notes: list[str]


def _figure3_jobs(direction: str, variant: str) -> bool:
    return variant in ("none", "cot") or (variant == REFERENCE and direction == "bwd")


def figure4_map(cells: Cells) -> tuple[str, str] | None:
    """The map shown in Figure 4: the paper's (BWD marking-deadend) if it ran, else our best map."""
    if len(cells("reachable", "bwd", REFERENCE)):
        return ("bwd", REFERENCE)
    ranked = [(rate_stats(cells("reachable", d, v), True)["rate"], d, v)
              for d in cells.directions for v in MAP_VARIANTS
              if len(cells("reachable", d, v))]
    return max(ranked)[1:] if ranked else None


def write_figures(data: StoreData, out: Path) -> tuple[list[Path], dict[str, pd.DataFrame]]:
    """Every figure (and Figure 4's fits as a table); figures without data are left out."""
    from pipeline.report import figures as figs

    paths = figs.size_heatmaps(data.episodes, out)
    fig4, fits = figs.moves_vs_optimal(data.episodes, out, figure4_map(Cells(data.episodes)))
    fig3 = figs.rapid_adaptation(data.curves, data.losses, out, keep=_figure3_jobs)
    paths += [p for p in (fig4, fig3) if p is not None]
    for job in data.jobs:
        name = f"gallery_{job.mode}_{job.direction}_{job.variant}_seed{job.seed}.png"
        path = figs.episode_gallery(data.galleries.get(job.run_id, []), job.label, out / name)
        if path is not None:
            paths.append(path)
    return paths, {"fig4_fits": fits}


def _clear(folder: Path) -> None:
    """Remove a previous report's files, so a smaller grid leaves no stale tables or figures."""
    if folder.is_dir():
        for old in folder.iterdir():
            if old.is_file() and old.suffix in (".md", ".csv", ".png"):
                old.unlink()


def render_index(data: StoreData, tracking_uri: str, tables: dict[str, pd.DataFrame],
                 out: Path, paths: list[Path]) -> str:
    """``report.md``: what was read, the headline tables inline, and links to every registered table and figure."""
    def link(p: Path) -> str:
        return p.relative_to(out).as_posix()

    lines = [f"# Report: experiment `{data.experiment}`", "",
             f"Store: `{tracking_uri}`. Finished job runs used: {len(data.jobs)} "
             f"({data.episodes['job_run_id'].nunique() if len(data.episodes) else 0} with episodes, "
             f"{len(data.episodes)} episodes).", ""]
    if not data.jobs:
        lines += ["**No finished job runs in this experiment yet: every cell below is 'not run'.**", ""]
    if data.notes:
        lines += ["Notes:", "", *(f"- {n}" for n in data.notes), ""]
    lines += ["## Tables", ""]
    for table in TABLES.values():
        csv = f"tables/{table.key}.csv"
        lines.append(f"- [{table.title}](tables/{table.key}.md) ([csv]({csv}))" if table.render is not None
                     else f"- [{table.title}]({csv})")
    lines.append("")
    for table in SUCCESS_TABLES:
        section = table.markdown(tables[table.key]).split("\n## ")[1]  # the 'all' section
        lines += [f"### {table.title} (all test worlds)", "", section.split("\n", 2)[2].strip(), ""]
    table3_body = TABLES["table3"].markdown(tables["table3"]).split("\n\n")[-1].strip()
    lines += ["### Table 3 (reachable)", "", table3_body, "", SEED_FOOTNOTE, "", "## Figures", ""]
    figures = [p for p in paths if p.suffix == ".png"]
    if not figures:
        lines += ["No figure: no job has episodes, checkpoint curves or training losses yet.", ""]
    for p in figures:
        lines += [f"### {p.stem}", "", f"![{p.stem}]({link(p)})", ""]
    return "\n".join(lines)


def log_report_run(tracking_uri: str, experiment_id: str, out: Path, paths: list[Path],
                   n_jobs: int) -> str:
    """A new top-level run tagged ``cogmap.kind=report`` holding ``paths`` as artifacts."""
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=tracking_uri)
    # The client API (not mlflow.start_run) so an active run or MLFLOW_RUN_ID cannot make it nested.
    run = client.create_run(experiment_id, tags={KIND_TAG: REPORT_KIND}, run_name="report")
    try:
        for path in paths:
            parent = path.parent.relative_to(out).as_posix()
            client.log_artifact(run.info.run_id, str(path), None if parent == "." else parent)
        client.log_metric(run.info.run_id, "n_jobs", n_jobs)
    except Exception:
        client.set_terminated(run.info.run_id, "FAILED")
        raise
    client.set_terminated(run.info.run_id, "FINISHED")
    return run.info.run_id


def build_report(tracking_uri: str, experiment: str, out_dir: str | Path, *,
                 log_run: bool = True) -> ReportResult:
    """Read the experiment's finished jobs and write tables, figures and ``report.md`` under ``out_dir``.

    With ``log_run`` the written files are also logged as artifacts of a new ``cogmap.kind=report`` run.
    Raises :class:`ReportError` if the store or the experiment does not exist.
    """
    data = load_store(tracking_uri, experiment)
    out = Path(out_dir)
    for folder in (out / "tables", out / "figures"):
        _clear(folder)
    tables = compute_tables(data)
    figure_paths, figure_tables = write_figures(data, out / "figures")
    tables |= figure_tables
    paths = write_tables(tables, out / "tables") + figure_paths
    index = out / "report.md"
    index.write_text(render_index(data, tracking_uri, tables, out, paths), encoding="utf-8")
    paths.append(index)
    run_id = None
    if log_run:
        _, exp = open_experiment(tracking_uri, experiment)
        run_id = log_report_run(tracking_uri, exp.experiment_id, out, paths, len(data.jobs))
    return ReportResult(out, paths, tables, run_id, data.notes)


class ReportCallback(Callback):
    """Hydra callback: build the report when a multirun ends (a failure is a warning, never an error)."""

    def __init__(self, tracking_uri: str, experiment: str, out_dir: str) -> None:
        self.tracking_uri, self.experiment, self.out_dir = tracking_uri, experiment, out_dir
        self._built = False

    def on_multirun_start(self, config, **kwargs) -> None:
        # Hydra skips on_multirun_end when a job failed (the sweeper re-raises): build at exit instead.
        atexit.register(self._build_if_missing)

    def _build_if_missing(self) -> None:
        if not self._built:
            self.on_multirun_end(None)

    def on_multirun_end(self, config, **kwargs) -> None:
        self._built = True
        try:
            result = build_report(self.tracking_uri, self.experiment, self.out_dir)
            log.info("Report written to %s (MLflow run %s)", result.out_dir / "report.md",
                     result.run_id)
        except Exception:  # noqa: BLE001 (the sweep's results are in MLflow whatever happens here)
            log.warning("Could not build the report after the multirun", exc_info=True)


def main(argv: list[str] | None = None) -> int:
    """``python -m pipeline.report``: build the report from the MLflow store; exit code 2 on a bad store."""
    parser = argparse.ArgumentParser(prog="python -m pipeline.report", description=__doc__.split("\n")[0])
    add_store_arguments(parser)
    parser.add_argument("--out", default=None, help="output folder (default: report/ under tracking.root)")
    parser.add_argument("--no-log-run", action="store_true",
                        help="write the files only, without a report run in MLflow")
    args = parser.parse_intermixed_args(argv)  # tracking.root=DIR may follow the options
    tracking_uri, experiment = store_of(parser, args)
    root = next((item.partition("=")[2] for item in args.store if item.startswith("tracking.root=")), "outputs")
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        result = build_report(tracking_uri, experiment, args.out or str(Path(root) / "report"),
                              log_run=not args.no_log_run)
    except ReportError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    for note in result.notes:
        log.warning(note)
    print(f"Report: {result.out_dir / 'report.md'} ({len(result.paths)} files"
          + (f", MLflow run {result.run_id})" if result.run_id else ")"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
