"""Loading the report's inputs from the MLflow store alone: the latest finished job run of each cell, its eval
run's episodes (and checkpoint episodes), its metric histories and the worlds its gallery draws."""

from __future__ import annotations

import json
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import pandas as pd

from pipeline.core.episodes import EPISODE_FIELDS
from pipeline.core.map_errors import category, step_bucket
from pipeline.core.variants import DIRECTIONS, MODES, PAPER_ROWS, VARIANTS
from pipeline.core.world import load_worlds
from pipeline.workflow.data_build import TEST_WORLDS
from pipeline.workflow.tracking import (
    CURVE_EPISODES_ARTIFACT, CURVE_METRIC, EPISODES_ARTIFACT, JOB_KIND, KIND_TAG, TRAIN_MAX_TAGS, step_run_tag,
)

LOSS_METRIC = "loss"
JOB_COLUMNS = ("mode", "direction", "variant", "seed")


class ReportError(RuntimeError):
    """The report cannot be built (no such store or experiment)."""


@dataclass(frozen=True)
class Job:
    """One finished job run: its cell (mode, direction, variant, seed) and the step runs it used."""

    run_id: str
    mode: str
    direction: str
    variant: str
    seed: str
    paper_row: str
    eval_run_id: str | None
    finetune_run_id: str | None
    start_time: int
    train_max: tuple[int, int] | None = None   # (X, Y) from the job's tags; None for runs that predate them
    data_build_run_id: str | None = None

    @property
    def label(self) -> str:
        return f"{PAPER_ROWS.get(self.variant, self.variant)} ({self.direction.upper()}, {self.mode})"


@dataclass
class StoreData:
    """Everything the report reads from the store."""

    experiment: str
    jobs: list[Job]
    episodes: pd.DataFrame          # EPISODE_FIELDS (less moves) + JOB_COLUMNS + job/eval run ids
    curves: pd.DataFrame            # JOB_COLUMNS + job_run_id, step, value (curve_success_rate)
    losses: pd.DataFrame            # JOB_COLUMNS + finetune_run_id, step, value (training loss)
    notes: list[str] = field(default_factory=list)
    # JOB_COLUMNS + job_run_id, step, success, interpolated, wrong_category, wrong_step: checkpoint episodes
    curve_episodes: pd.DataFrame = field(default_factory=pd.DataFrame)
    # job run id -> (world, episode record) pairs the job's gallery figure draws
    galleries: dict[str, list[tuple]] = field(default_factory=dict)


def open_experiment(tracking_uri: str, experiment: str):
    """The client and experiment for ``tracking_uri``; :class:`ReportError` naming what does not exist."""
    from mlflow import MlflowClient
    from mlflow.exceptions import MlflowException

    if tracking_uri.startswith("sqlite:///"):
        # MLflow would silently create an empty store: refuse a database file that is not there.
        db = Path(tracking_uri.removeprefix("sqlite:///"))
        if tracking_uri.startswith("sqlite:////"):
            db = Path("/" + tracking_uri.removeprefix("sqlite:////"))
        if not db.is_file():
            raise ReportError(f"no MLflow store at {tracking_uri} (file {db} does not exist)")
    elif "://" not in tracking_uri or tracking_uri.startswith("file:"):
        path = Path(tracking_uri.removeprefix("file://").removeprefix("file:"))
        if not path.is_dir():
            raise ReportError(f"no MLflow store at {tracking_uri} (folder {path} does not exist)")
    client = MlflowClient(tracking_uri=tracking_uri)
    try:
        found = client.get_experiment_by_name(experiment)
    except MlflowException as err:
        raise ReportError(f"cannot read the MLflow store at {tracking_uri}: {err}") from err
    if found is None:
        raise ReportError(f"no experiment named {experiment!r} in the MLflow store at {tracking_uri}")
    return client, found


def _all_runs(client, experiment_id: str, filter_string: str) -> list:
    runs, token = [], None
    while True:
        page = client.search_runs([experiment_id], filter_string=filter_string, max_results=1000,
                                  page_token=token)
        runs.extend(page)
        token = page.token
        if not token:
            return runs


def finished_job_runs(client, experiment_id: str) -> list:
    """Every FINISHED job run of the experiment, oldest first."""
    runs = _all_runs(client, experiment_id, f"tags.`{KIND_TAG}` = '{JOB_KIND}' and attributes.status = 'FINISHED'")
    return sorted(runs, key=lambda run: run.info.start_time or 0)


def finished_jobs(client, experiment_id: str) -> tuple[list[Job], list[str]]:
    """The latest FINISHED job run per (mode, direction, variant, seed), and notes on what was skipped."""
    runs = _all_runs(client, experiment_id, f"tags.`{KIND_TAG}` = '{JOB_KIND}'")
    notes, latest = [], {}
    unfinished = [r for r in runs if r.info.status != "FINISHED"]
    if unfinished:
        notes.append(f"{len(unfinished)} job run(s) not FINISHED were ignored: "
                     + ", ".join(f"{r.info.run_id[:8]} ({r.info.status})" for r in unfinished))
    for run in runs:
        if run.info.status != "FINISHED":
            continue
        tags = run.data.tags
        job = Job(
            run_id=run.info.run_id,
            mode=str(tags.get("mode", "")).lower(),
            direction=str(tags.get("direction", "")).lower(),
            variant=str(tags.get("variant", "")).lower(),
            seed=str(tags.get("seed", "")),
            paper_row=tags.get("paper_row", ""),
            eval_run_id=tags.get(step_run_tag("eval")),
            finetune_run_id=tags.get(step_run_tag("finetune")),
            data_build_run_id=tags.get(step_run_tag("data-build")),
            start_time=run.info.start_time or 0,
            train_max=_train_max(tags),
        )
        key = (job.mode, job.direction, job.variant, job.seed)
        if key not in latest or job.start_time > latest[key].start_time:
            latest[key] = job
    superseded = sum(1 for r in runs if r.info.status == "FINISHED") - len(latest)
    if superseded:
        notes.append(f"{superseded} older finished job run(s) superseded by a later run of the same cell")
    order = {v: i for i, v in enumerate(VARIANTS)}
    jobs = sorted(latest.values(), key=lambda j: (
        _index(MODES, j.mode), _index(DIRECTIONS, j.direction), order.get(j.variant, len(order)),
        j.variant, _seed_key(j.seed)))
    return jobs, notes


def _train_max(tags: dict) -> tuple[int, int] | None:
    try:
        return int(tags[TRAIN_MAX_TAGS[0]]), int(tags[TRAIN_MAX_TAGS[1]])
    except (KeyError, ValueError):
        return None


def _index(seq: tuple[str, ...], value: str) -> int:
    return seq.index(value) if value in seq else len(seq)


def _seed_key(seed: str) -> tuple[int, float | str]:
    try:
        return (0, float(seed))
    except ValueError:
        return (1, seed)


def read_records(client, run_id: str, scratch: Path) -> list[dict]:
    """The eval run's ``episodes.jsonl`` records as written."""
    target = scratch / run_id
    target.mkdir(parents=True, exist_ok=True)
    return _jsonl(client.download_artifacts(run_id, EPISODES_ARTIFACT, str(target)))


def _jsonl(path: str | Path) -> list[dict]:
    with open(path, encoding="utf-8") as fh:
        return [json.loads(line) for line in fh if line.strip()]


def episodes_frame(records: list[dict]) -> pd.DataFrame:
    """Episode records as a DataFrame: typed columns, the first wrong line as category/step/state columns,
    without the move lists and raw answers (the report never reads them; `python -m pipeline.inspect` does)."""
    frame = pd.DataFrame.from_records(records)
    for name in EPISODE_FIELDS:
        if name not in frame.columns:
            frame[name] = None
    frame["success"] = frame["success"].fillna(False).astype(bool)
    for name in ("up_right_only", "interpolated", "parsed", "valid", "reaches_goal", "map_exact"):
        frame[name] = frame[name].astype("boolean")
    for name in ("size_x", "size_y", "optimal_length", "n_moves", "map_first_error"):
        frame[name] = pd.to_numeric(frame[name], errors="coerce")
    frame["outcome"] = frame["outcome"].astype("string").str.lower()
    sites = [site if isinstance(site, dict) else None for site in frame["first_wrong_line"]]
    frame["wrong_category"] = [category(site) if site else None for site in sites]
    frame["wrong_step"] = [step_bucket(site.get("step")) if site else None for site in sites]
    frame["wrong_state"] = pd.to_numeric(pd.Series([site.get("state") if site else None for site in sites],
                                                   index=frame.index, dtype=object), errors="coerce")
    return frame.drop(columns=["moves", "answers", "first_wrong_line"])


def read_curve_episodes(client, run_id: str, scratch: Path) -> pd.DataFrame:
    """The episodes of every evaluated checkpoint (``curve/step-<n>.jsonl``), with a ``step`` column."""
    entries = client.list_artifacts(run_id, CURVE_EPISODES_ARTIFACT)
    frames = []
    for entry in entries:
        name = Path(entry.path).name
        if entry.is_dir or not (name.startswith("step-") and name.endswith(".jsonl")):
            continue
        target = scratch / run_id / "curve"
        target.mkdir(parents=True, exist_ok=True)
        frame = episodes_frame(_jsonl(client.download_artifacts(run_id, entry.path, str(target))))
        frames.append(frame.assign(step=int(name[len("step-"):-len(".jsonl")])))
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def _history(client, run_id: str, key: str) -> pd.DataFrame:
    metrics = client.get_metric_history(run_id, key)
    frame = pd.DataFrame({"step": [m.step for m in metrics], "value": [m.value for m in metrics]})
    # A metric logged twice at one step (e.g. a resumed run): keep the last value.
    return frame.drop_duplicates("step", keep="last").sort_values("step")


def load_store(tracking_uri: str, experiment: str) -> StoreData:
    """Read the experiment's finished jobs, their episodes, checkpoint curves and training losses."""
    client, exp = open_experiment(tracking_uri, experiment)
    jobs, notes = finished_jobs(client, exp.experiment_id)
    episodes, curves, losses, curve_episodes = [], [], [], []
    cache: dict[str, pd.DataFrame | None] = {}
    picks: dict[str, list[dict]] = {}
    galleries: dict[str, list[tuple]] = {}
    test_worlds: dict[str, list] = {}
    curve_cache: dict[str, pd.DataFrame] = {}
    # matplotlib comes with report_figures: imported here, not when a job loads the report callback.
    from pipeline.report.figures import gallery_picks

    with tempfile.TemporaryDirectory() as scratch:
        for job in jobs:
            cell = {"mode": job.mode, "direction": job.direction, "variant": job.variant,
                    "seed": job.seed}
            if not job.eval_run_id:
                notes.append(f"job {job.run_id[:8]} {job.label}: no eval run tag; shown as not run")
                continue
            if job.eval_run_id not in cache:  # a reused eval run is read once
                try:
                    records = read_records(client, job.eval_run_id, Path(scratch))
                    cache[job.eval_run_id] = episodes_frame(records)
                    picks[job.eval_run_id] = gallery_picks(records)
                except Exception as err:  # noqa: BLE001 (a broken job must not stop the report)
                    cache[job.eval_run_id] = None
                    notes.append(f"eval run {job.eval_run_id[:8]} ({job.label}): cannot read "
                                 f"{EPISODES_ARTIFACT} (shown as not run): {err}")
            frame = cache[job.eval_run_id]
            if frame is not None and picks.get(job.eval_run_id):
                data_id = job.data_build_run_id
                try:
                    if data_id and data_id not in test_worlds:
                        test_worlds[data_id] = load_worlds(client.download_artifacts(
                            data_id, TEST_WORLDS, str(Path(scratch) / data_id)))
                    worlds = test_worlds.get(data_id) or []
                    galleries[job.run_id] = [(worlds[r["world_index"]], r) for r in picks[job.eval_run_id]
                                             if r["world_index"] < len(worlds)]
                except Exception as err:  # noqa: BLE001 (a gallery is not worth failing the report)
                    notes.append(f"job {job.run_id[:8]} ({job.label}): no gallery, cannot read its test worlds: {err}")
            if frame is not None:
                box = job.train_max or (None, None)
                episodes.append(frame.assign(**cell, job_run_id=job.run_id, eval_run_id=job.eval_run_id,
                                             train_max_x=box[0], train_max_y=box[1]))
                curve = _history(client, job.eval_run_id, CURVE_METRIC)
                if len(curve):
                    curves.append(curve.assign(**cell, job_run_id=job.run_id))
                    if job.eval_run_id not in curve_cache:  # a reused eval run is read once
                        try:
                            curve_cache[job.eval_run_id] = read_curve_episodes(client, job.eval_run_id, Path(scratch))
                        except Exception as err:  # noqa: BLE001 (older runs have no curve episodes)
                            notes.append(f"eval run {job.eval_run_id[:8]} ({job.label}): cannot read its "
                                         f"checkpoint episodes: {err}")
                            curve_cache[job.eval_run_id] = pd.DataFrame()
                    checkpoints = curve_cache[job.eval_run_id]
                    if len(checkpoints):
                        curve_episodes.append(checkpoints.assign(**cell, job_run_id=job.run_id))
            if job.finetune_run_id:
                loss = _history(client, job.finetune_run_id, LOSS_METRIC)
                if len(loss):
                    losses.append(loss.assign(**cell, finetune_run_id=job.finetune_run_id))
    episode_columns = [*(f for f in EPISODE_FIELDS if f not in ("moves", "answers", "first_wrong_line")),
                       "wrong_category", "wrong_step", "wrong_state", *JOB_COLUMNS, "job_run_id",
                       "eval_run_id", *TRAIN_MAX_TAGS]
    return StoreData(
        experiment=experiment,
        jobs=jobs,
        episodes=pd.concat(episodes, ignore_index=True) if episodes
        else pd.DataFrame(columns=episode_columns),
        curves=pd.concat(curves, ignore_index=True) if curves
        else pd.DataFrame(columns=[*JOB_COLUMNS, "job_run_id", "step", "value"]),
        losses=pd.concat(losses, ignore_index=True) if losses
        else pd.DataFrame(columns=[*JOB_COLUMNS, "finetune_run_id", "step", "value"]),
        notes=notes,
        curve_episodes=pd.concat(curve_episodes, ignore_index=True) if curve_episodes else pd.DataFrame(),
        galleries=galleries,
    )
