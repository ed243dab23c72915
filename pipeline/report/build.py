"""The report: the paper's tables and figures, from the MLflow store only.

``python -m pipeline.report`` (and :class:`ReportCallback` at the end of every multirun) reads the finished
job runs of an experiment (layout in :mod:`pipeline.workflow.tracking`), their eval runs' ``episodes.jsonl`` and
metric histories, and writes Markdown/CSV tables, PNG figures and an index ``report.md`` under ``out_dir``;
the same files are logged as artifacts of a new run tagged ``cogmap.kind=report``.

Every rate is over episodes; an episode that could not run (``outcome == "error"``) counts as a failure.
Several seeds in one cell: the rate is the mean of the per-seed rates, the interval the 95% Wilson interval
of all episodes pooled over seeds, and the per-seed range is printed beside it.
"""

from __future__ import annotations

import argparse
import atexit
import json
import logging
import math
import os
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterable

import pandas as pd
from hydra.experimental.callback import Callback

from pipeline.core.episodes import EPISODE_FIELDS
from pipeline.core.variants import DIRECTIONS, MAP_VARIANTS, MODES, PAPER_ROWS, REFERENCE, SUCCESS_TABLE_ROWS, VARIANTS
from pipeline.workflow.data_build import TEST_WORLDS
from pipeline.core.map_errors import STEP_BUCKETS, category, step_bucket
from pipeline.core.world import load_worlds
from pipeline.report.stats import mcnemar, seeded_rate
from pipeline.workflow.tracking import (
    CURVE_EPISODES_ARTIFACT,
    CURVE_METRIC,
    EPISODES_ARTIFACT,
    JOB_KIND,
    KIND_TAG,
    REPORT_KIND,
    TRAIN_MAX_TAGS,
    default_tracking_uri,
    step_run_tag,
)

log = logging.getLogger(__name__)

REFERENCE_VARIANT = REFERENCE
LOSS_METRIC = "loss"

# SPEC 5: the paper's success rates, (mode, variant) -> (FWD, BWD). NONE is direction-independent
# (one number printed in both columns); DFS (Table 3) is reachable-only and direction-independent.
PAPER_SUCCESS: dict[tuple[str, str], tuple[float, float]] = {
    ("optimal", "none"): (0.190, 0.190),
    ("optimal", "cot"): (0.252, 0.265),
    ("optimal", "marking-deadend"): (0.585, 0.705),
    ("optimal", "no-marking"): (0.618, 0.765),
    ("reachable", "none"): (0.321, 0.321),
    ("reachable", "cot"): (0.339, 0.287),
    ("reachable", "marking-deadend"): (0.854, 0.885),
    ("reachable", "no-marking"): (0.816, 0.724),
    ("optimal", "no-all-no-backtrack"): (0.295, 0.296),
    ("optimal", "no-all"): (0.290, 0.277),
    ("reachable", "no-all-no-backtrack"): (0.416, 0.394),
    ("reachable", "no-all"): (0.345, 0.283),
    ("optimal", "no-marking-no-backtrack"): (0.528, 0.406),
    ("optimal", "no-backtrack"): (0.516, 0.423),
    ("reachable", "no-marking-no-backtrack"): (0.672, 0.739),
    ("reachable", "no-backtrack"): (0.624, 0.852),
    ("reachable", "dfs"): (0.945, 0.945),
}

# Tables 1, 7 and 8 (and ours): title and rows (variants; core.variants.SUCCESS_TABLE_ROWS) by mode x direction.
_TITLES = {
    "table1": "Table 1: success rate, baselines and the cognitive map",
    "table7": "Table 7: success rate without ALL (only new neighbours listed)",
    "table8": "Table 8: success rate without BACKTRACK",
    "table_named": "Beyond the paper: each expanded state named (`From (x, y):` before its neighbours)",
}
SUCCESS_TABLES = {key: (_TITLES[key], rows) for key, rows in SUCCESS_TABLE_ROWS.items()}

# Every table is also split by these subsets of the test worlds (name -> episode filter).
SUBSETS: dict[str, Callable[[pd.DataFrame], pd.Series]] = {
    "all": lambda e: pd.Series(True, index=e.index),
    "up/right only": lambda e: e["up_right_only"] == True,  # noqa: E712 (nullable column)
    "needs down/left": lambda e: e["up_right_only"] == False,  # noqa: E712
    "interpolated": lambda e: e["interpolated"] == True,  # noqa: E712
    "extrapolated": lambda e: e["interpolated"] == False,  # noqa: E712
}

JOB_COLUMNS = ("mode", "direction", "variant", "seed")
MISSING = "not run"

SEED_FOOTNOTE = (
    "Cells: our success rate, its 95% Wilson interval in brackets, the paper's number (SPEC 5) after "
    "'paper'. With several seeds the rate is the mean of the per-seed rates, the interval the Wilson "
    "interval of all episodes pooled over seeds (it ignores seed-to-seed variance), and the per-seed "
    "range follows in braces. Episodes that could not run count as failures. 'not run' = no finished "
    "job for that cell (never read as 0); 'n=0' = the job ran but has no episode in this subset.")


class ReportError(RuntimeError):
    """The report cannot be built (no such store or experiment)."""


# ---------------------------------------------------------------------------------------------- loading


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


# ----------------------------------------------------------------------------------------------- tables


def directions_of(episodes: pd.DataFrame) -> list[str]:
    """fwd and bwd, then any other direction tag found in the data."""
    extra = sorted(set(episodes["direction"].dropna()) - set(DIRECTIONS))
    return [*DIRECTIONS, *extra]


def paper_success(mode: str, variant: str, direction: str) -> float:
    """The paper's success rate for a cell (SPEC 5), nan where the paper has none."""
    pair = PAPER_SUCCESS.get((mode, variant))
    if pair is None:
        return math.nan
    if direction in DIRECTIONS:
        return pair[DIRECTIONS.index(direction)]
    return pair[0] if pair[0] == pair[1] else math.nan  # direction-independent rows only


class Cells:
    """The episodes grouped by job cell (mode, direction, variant); a cell that did not run is empty."""

    def __init__(self, episodes: pd.DataFrame) -> None:
        self.episodes = episodes
        self.directions = directions_of(episodes)
        self._groups = dict(iter(episodes.groupby(["mode", "direction", "variant"], sort=False)))
        self._empty = episodes.iloc[0:0]

    def __call__(self, mode: str, direction: str, variant: str) -> pd.DataFrame:
        return self._groups.get((mode, direction, variant), self._empty)

    def present(self, mode: str) -> list[tuple[str, str]]:
        """The (direction, variant) cells that ran in ``mode``, in table order."""
        order = {v: i for i, v in enumerate(VARIANTS)}
        return sorted(((d, v) for m, d, v in self._groups if m == mode),
                      key=lambda dv: (_index(DIRECTIONS, dv[0]), dv[0], order.get(dv[1], 99), dv[1]))


def _subset(frame: pd.DataFrame, subset: str) -> pd.DataFrame:
    return frame[SUBSETS[subset](frame).fillna(False).astype(bool)]


def _seed_mean(frame: pd.DataFrame, column: str) -> float:
    """Mean over seeds of the per-seed mean of ``column`` (nulls skipped); nan without values."""
    values = frame.groupby("seed")[column].apply(
        lambda s: pd.to_numeric(s, errors="coerce").astype(float).mean())
    values = values.dropna()
    return float(values.mean()) if len(values) else math.nan


def rate_stats(frame: pd.DataFrame, ran: bool) -> dict:
    """Success statistics of one cell's episodes: status, counts, rate, Wilson interval, seed spread."""
    if not ran:
        return {"status": MISSING, "n_seeds": 0, "n": 0, "successes": 0, "rate": math.nan,
                "ci_low": math.nan, "ci_high": math.nan, "seed_min": math.nan,
                "seed_max": math.nan, "seed_sd": math.nan}
    rate = seeded_rate([(int(g["success"].sum()), len(g)) for _, g in frame.groupby("seed")])
    return {"status": "ok" if rate.n else "n=0", "n_seeds": rate.n_seeds, "n": rate.n,
            "successes": rate.successes, "rate": rate.rate, "ci_low": rate.ci_low,
            "ci_high": rate.ci_high, "seed_min": rate.seed_min, "seed_max": rate.seed_max,
            "seed_sd": rate.seed_sd}


def success_table(cells: Cells, variants: Iterable[str]) -> pd.DataFrame:
    """Long table: one row per subset x mode x direction x variant with our rate and the paper's."""
    rows = []
    for subset in SUBSETS:
        for mode in MODES:
            for direction in cells.directions:
                for variant in variants:
                    cell = cells(mode, direction, variant)
                    rows.append({
                        "subset": subset, "mode": mode, "direction": direction, "variant": variant,
                        "paper_row": PAPER_ROWS.get(variant, variant),
                        **rate_stats(_subset(cell, subset), ran=len(cell) > 0),
                        "paper": paper_success(mode, variant, direction) if subset == "all"
                        else math.nan,
                    })
    return pd.DataFrame(rows)


def table3(cells: Cells) -> pd.DataFrame:
    """Table 3 (reachable): the paper's cognitive map (BWD marking-deadend), our best map, and DFS."""
    entries = [("cognitive map (BWD MARKING deadend)", "bwd", REFERENCE_VARIANT)]
    ranked = [(rate_stats(cells("reachable", d, v), True)["rate"], d, v)
              for d in cells.directions for v in MAP_VARIANTS
              if len(cells("reachable", d, v))]
    if ranked:
        _, d, v = max(ranked)
        if (d, v) != ("bwd", REFERENCE_VARIANT):
            entries.append((f"best cognitive map of ours ({d.upper()} {PAPER_ROWS[v]})", d, v))
    dfs_directions = [d for d in cells.directions if len(cells("reachable", d, "dfs"))]
    entries += [(f"DFS exploration ({d.upper()} run)", d, "dfs") for d in dfs_directions] or [
        ("DFS exploration", "bwd", "dfs")]
    rows = []
    for subset in SUBSETS:
        for label, direction, variant in entries:
            cell = cells("reachable", direction, variant)
            part = _subset(cell, subset)
            won = part[part["success"]]
            rows.append({
                "subset": subset, "row": label, "mode": "reachable", "direction": direction,
                "variant": variant, **rate_stats(part, ran=len(cell) > 0),
                "moves_over_optimal": _seed_mean(
                    won.assign(ratio=won["n_moves"] / won["optimal_length"]), "ratio")
                if len(won) else math.nan,
                "paper": paper_success("reachable", variant, direction) if subset == "all"
                else math.nan,
            })
    return pd.DataFrame(rows)


def _paired(cells: Cells, mode: str, direction: str, variant: str, reference: str,
            subset: str) -> tuple[pd.DataFrame, list[str]]:
    """Outcomes of ``variant`` and ``reference`` on shared (seed, world) pairs.

    Shared seeds are paired seed by seed; with no seed in common, the lowest seed of each is paired.
    """
    a = _subset(cells(mode, direction, variant), subset)
    b = _subset(cells(mode, direction, reference), subset)
    seeds = sorted(set(a["seed"]) & set(b["seed"]), key=_seed_key)
    if seeds:
        a, b = a[a["seed"].isin(seeds)], b[b["seed"].isin(seeds)]
    elif len(a) and len(b):
        sa, sb = min(set(a["seed"]), key=_seed_key), min(set(b["seed"]), key=_seed_key)
        a, b = a[a["seed"] == sa].assign(seed=sb), b[b["seed"] == sb]
        seeds = [f"{sa}~{sb}"]
    keys = ["seed", "world_index"]
    merged = a[[*keys, "success"]].drop_duplicates(keys).merge(
        b[[*keys, "success"]].drop_duplicates(keys), on=keys, suffixes=("_a", "_b"))
    return merged, seeds


def mcnemar_table(cells: Cells) -> pd.DataFrame:
    """Each variant against its direction's marking-deadend (same mode), paired on shared test worlds."""
    rows = []
    for subset in SUBSETS:
        for mode in MODES:
            for direction in cells.directions:
                if not len(cells(mode, direction, REFERENCE_VARIANT)):
                    continue
                for variant in VARIANTS:
                    if variant == REFERENCE_VARIANT or not len(cells(mode, direction, variant)):
                        continue
                    pairs, seeds = _paired(cells, mode, direction, variant, REFERENCE_VARIANT,
                                           subset)
                    test = mcnemar(pairs["success_a"].tolist(), pairs["success_b"].tolist())
                    n = test.n_pairs
                    rows.append({
                        "subset": subset, "mode": mode, "direction": direction, "variant": variant,
                        "reference": REFERENCE_VARIANT, "seeds": ",".join(map(str, seeds)),
                        "n_pairs": n,
                        "rate_variant": (test.both + test.only_a) / n if n else math.nan,
                        "rate_reference": (test.both + test.only_b) / n if n else math.nan,
                        "only_variant": test.only_a, "only_reference": test.only_b,
                        "both": test.both, "neither": test.neither,
                        "p_value": test.p_value if n else math.nan,
                    })
    return pd.DataFrame(rows, columns=[
        "subset", "mode", "direction", "variant", "reference", "seeds", "n_pairs", "rate_variant",
        "rate_reference", "only_variant", "only_reference", "both", "neither", "p_value"])


def graded_table(cells: Cells) -> pd.DataFrame:
    """Optimal setting, graded (SPEC 4): parsed, valid, reaches goal, success, map exact, first map error."""
    rows = []
    for subset in SUBSETS:
        for direction, variant in cells.present("optimal"):
            part = _subset(cells("optimal", direction, variant), subset)
            wrong = pd.to_numeric(part.loc[part["map_exact"] == False, "map_first_error"],  # noqa: E712
                                  errors="coerce").dropna()
            rows.append({
                "subset": subset, "direction": direction, "variant": variant, "n": len(part),
                **{f"rate_{c}": _seed_mean(part, c)
                   for c in ("parsed", "valid", "reaches_goal", "success", "map_exact")},
                "n_map_wrong": int((part["map_exact"] == False).sum()),  # noqa: E712
                "first_error_q1": wrong.quantile(0.25) if len(wrong) else math.nan,
                "first_error_median": wrong.median() if len(wrong) else math.nan,
                "first_error_q3": wrong.quantile(0.75) if len(wrong) else math.nan,
            })
    return pd.DataFrame(rows, columns=[
        "subset", "direction", "variant", "n", "rate_parsed", "rate_valid", "rate_reaches_goal",
        "rate_success", "rate_map_exact", "n_map_wrong", "first_error_q1", "first_error_median",
        "first_error_q3"])


MAP_ERROR_SUBSETS = ("all", "interpolated", "extrapolated")


def map_errors_table(cells: Cells) -> pd.DataFrame:
    """Optimal setting: the failing episodes of each map job by the kind of their first wrong line
    (map_errors.category), split by BFS step and by whether the state being expanded was the first on its
    frontier."""
    rows = []
    for subset in MAP_ERROR_SUBSETS:
        for direction, variant in cells.present("optimal"):
            part = _subset(cells("optimal", direction, variant), subset)
            failed = part[~part["success"] & part["wrong_category"].notna()]
            for name, block in failed.groupby("wrong_category", sort=True):
                steps = block["wrong_step"].value_counts()
                rows.append({
                    "subset": subset, "direction": direction, "variant": variant, "category": name,
                    "n": len(block), "share": len(block) / len(failed),
                    **{bucket: int(steps.get(bucket, 0)) for bucket in STEP_BUCKETS},
                    "later_frontier_state": int((block["wrong_state"] > 0).sum()),
                })
    return pd.DataFrame(rows, columns=["subset", "direction", "variant", "category", "n", "share",
                                       *STEP_BUCKETS, "later_frontier_state"])


def map_errors_by_step_table(curve_episodes: pd.DataFrame) -> pd.DataFrame:
    """How the kinds of first wrong lines move with training: for each job whose checkpoints were evaluated
    (optimal setting), per checkpoint step and subset, the failing episodes by category."""
    columns = ["subset", "direction", "variant", "seed", "step", "n_episodes", "success_rate", "category", "n",
               "share"]
    if curve_episodes.empty:
        return pd.DataFrame(columns=columns)
    rows = []
    optimal = curve_episodes[curve_episodes["mode"] == "optimal"]
    for subset in MAP_ERROR_SUBSETS:
        part = _subset(optimal, subset)
        for (direction, variant, seed, step), block in part.groupby(["direction", "variant", "seed", "step"],
                                                                    sort=True):
            failed = block[~block["success"] & block["wrong_category"].notna()]
            for name, group in failed.groupby("wrong_category", sort=True):
                rows.append({"subset": subset, "direction": direction, "variant": variant, "seed": seed,
                             "step": int(step), "n_episodes": len(block), "success_rate": block["success"].mean(),
                             "category": name, "n": len(group), "share": len(group) / len(failed)})
    return pd.DataFrame(rows, columns=columns)


REACHABLE_OUTCOMES = ("success", "deadend", "max_step", "invalid", "error")


def outcomes_table(cells: Cells) -> pd.DataFrame:
    """Reachable setting: the rate of each outcome per job cell, and moves over optimal on successes."""
    rows = []
    for subset in SUBSETS:
        for direction, variant in cells.present("reachable"):
            part = _subset(cells("reachable", direction, variant), subset)
            won = part[part["success"]]
            rows.append({
                "subset": subset, "direction": direction, "variant": variant, "n": len(part),
                **{f"rate_{o}": _seed_mean(part.assign(hit=part["outcome"] == o), "hit")
                   for o in REACHABLE_OUTCOMES},
                "moves_over_optimal": _seed_mean(
                    won.assign(ratio=won["n_moves"] / won["optimal_length"]), "ratio")
                if len(won) else math.nan,
            })
    return pd.DataFrame(rows, columns=[
        "subset", "direction", "variant", "n", *(f"rate_{o}" for o in REACHABLE_OUTCOMES),
        "moves_over_optimal"])


def jobs_table(jobs: list[Job]) -> pd.DataFrame:
    """The job runs the report used, with their step runs."""
    return pd.DataFrame([{"mode": j.mode, "direction": j.direction, "variant": j.variant,
                          "seed": j.seed, "paper_row": j.paper_row, "job_run_id": j.run_id,
                          "eval_run_id": j.eval_run_id, "finetune_run_id": j.finetune_run_id}
                         for j in jobs],
                        columns=["mode", "direction", "variant", "seed", "paper_row", "job_run_id",
                                 "eval_run_id", "finetune_run_id"])


def compute_tables(data: StoreData) -> dict[str, pd.DataFrame]:
    """Every table of the report, in long form (the CSV files)."""
    cells = Cells(data.episodes)
    tables = {key: success_table(cells, variants) for key, (_, variants) in SUCCESS_TABLES.items()}
    tables["table3"] = table3(cells)
    tables["mcnemar"] = mcnemar_table(cells)
    tables["graded_optimal"] = graded_table(cells)
    tables["map_errors"] = map_errors_table(cells)
    tables["map_errors_by_step"] = map_errors_by_step_table(data.curve_episodes)
    tables["outcomes_reachable"] = outcomes_table(cells)
    tables["jobs"] = jobs_table(data.jobs)
    return tables


# ---------------------------------------------------------------------------------------------- writing


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
    "Optimal setting, graded (SPEC 4): the share of episodes whose plan parsed, stayed valid (never left "
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


# ----------------------------------------------------------------------------------------------- report


@dataclass
class ReportResult:
    """What :func:`build_report` wrote: every path, the tables (long form), the report run's id."""

    out_dir: Path
    paths: list[Path]
    tables: dict[str, pd.DataFrame]
    run_id: str | None
    notes: list[str]


def _figure3_jobs(direction: str, variant: str) -> bool:
    return variant in ("none", "cot") or (variant == REFERENCE_VARIANT and direction == "bwd")


def figure4_map(cells: Cells) -> tuple[str, str] | None:
    """The map shown in Figure 4: the paper's (BWD marking-deadend) if it ran, else our best map."""
    if len(cells("reachable", "bwd", REFERENCE_VARIANT)):
        return ("bwd", REFERENCE_VARIANT)
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
    """``report.md``: what was read, the headline tables inline, and links to every file."""
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
    for key, (title, _) in SUCCESS_TABLES.items():
        lines.append(f"- [{title}](tables/{key}.md) ([csv](tables/{key}.csv))")
    lines += ["- [Table 3: cognitive map vs DFS](tables/table3.md) ([csv](tables/table3.csv))",
              "- [Paired tests against marking-deadend](tables/mcnemar.md)"
              " ([csv](tables/mcnemar.csv))",
              "- [Optimal setting, graded](tables/graded_optimal.md)"
              " ([csv](tables/graded_optimal.csv))",
              "- [Reachable setting, outcomes](tables/outcomes_reachable.md)"
              " ([csv](tables/outcomes_reachable.csv))",
              "- [Where failing answers first go wrong](tables/map_errors.md) ([csv](tables/map_errors.csv)),"
              " [by training step](tables/map_errors_by_step.md) ([csv](tables/map_errors_by_step.csv))",
              "- [Job runs used](tables/jobs.csv)", ""]
    for key, (title, _) in SUCCESS_TABLES.items():
        section = render_success(title, tables[key]).split("\n## ")[1]  # the 'all' section
        lines += [f"### {title} (all test worlds)", "", section.split("\n", 2)[2].strip(), ""]
    lines += ["### Table 3 (reachable)", "", render_table3(tables["table3"]).split("\n\n")[-1].strip(),
              "", SEED_FOOTNOTE, "", "## Figures", ""]
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
    parser.add_argument("--tracking-uri", default=default_tracking_uri(),
                        help="MLflow tracking URI (default: %(default)s)")
    parser.add_argument("--experiment", default="cogmap", help="experiment name (default: %(default)s)")
    parser.add_argument("--out", default="outputs/report", help="output folder (default: %(default)s)")
    parser.add_argument("--no-log-run", action="store_true",
                        help="write the files only, without a report run in MLflow")
    args = parser.parse_args(argv)
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # one bar per eval run
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(message)s")
    try:
        result = build_report(args.tracking_uri, args.experiment, args.out,
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
