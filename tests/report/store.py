"""The small synthetic MLflow store the report's tests read: test worlds, episodes with known outcomes, and
job runs in the layout of pipeline.workflow.tracking, built with the MLflow client."""

from __future__ import annotations

import json
import time

from pipeline.core import variants
from pipeline.workflow.tracking import (CURVE_METRIC, EPISODES_ARTIFACT, JOB_KIND, KIND_TAG, STEP_KIND, STEP_TAG,
                                        ensure_experiment, step_run_tag)

N = 40
FWD_MD_WINS = set(range(30))                          # 30/40
FWD_NM_WINS = set(range(5, 25)) | {30, 31, 32, 33}     # 24/40: 20 shared, 4 only here, 10 only in md


def world(i: int) -> dict:
    """Test world i: sizes 2..8, even worlds up/right only, train maximum 5."""
    sx, sy = 2 + i % 7, 2 + (i // 7) % 7
    return {"world_index": i, "size_x": sx, "size_y": sy, "up_right_only": i % 2 == 0,
            "interpolated": sx <= 5 and sy <= 5, "dead_ends": i % 3,
            "optimal_length": sx + sy - 2 + (0 if i % 2 == 0 else 2)}


def episodes(mode: str, wins: set[int], dfs: bool = False) -> list[dict]:
    """The N episode records of one eval run: the worlds in ``wins`` succeed, the others fail in turn."""
    records = []
    for i in range(N):
        w, ok = world(i), i in wins
        n = w["optimal_length"]
        if mode == "reachable":
            outcome = "success" if ok else ("deadend", "max_step", "invalid", "error")[i % 4]
            extra = {"n_moves": (n * n if dfs else n) if ok else 3, "parsed": None, "valid": None,
                     "reaches_goal": None, "map_exact": None, "map_first_error": None}
        else:
            outcome = "success" if ok else "fail"
            extra = {"n_moves": n, "parsed": True, "valid": ok or i % 2 == 0,
                     "reaches_goal": ok or i % 4 == 0, "map_exact": ok,
                     "map_first_error": None if ok else 1 + i % 5}
        records.append({**w, "success": ok, "outcome": outcome, "moves": ["up"] * extra["n_moves"],
                        "error": "prompt too long" if outcome == "error" else None, **extra})
    return records


class Store:
    """Builds runs in the layout of pipeline.workflow.tracking with the MLflow client."""

    def __init__(self, tmp_path):
        from mlflow import MlflowClient

        self.uri = f"sqlite:///{tmp_path}/mlflow.db"
        self.exp_id = ensure_experiment(self.uri, "cogmap", str(tmp_path / "artifacts"))
        self.client = MlflowClient(self.uri)
        self.tmp = tmp_path
        self.clock = int(time.time() * 1000) - 10_000_000

    def _run(self, tags: dict, parent: str | None = None) -> str:
        self.clock += 1000
        if parent:
            tags = {**tags, "mlflow.parentRunId": parent}
        return self.client.create_run(self.exp_id, start_time=self.clock, tags=tags).info.run_id

    def _history(self, run_id: str, key: str, points: list[tuple[int, float]]) -> None:
        for step, value in points:
            self.client.log_metric(run_id, key, value, step=step)

    def job(self, mode, direction, variant, seed=0, *, wins=None, status="FINISHED",
            eval_run=None, loss=None, curve=None, artifact=True, job_tags=None) -> tuple[str, str]:
        """A job run with nested finetune and eval runs (or pointing at ``eval_run``)."""
        job = self._run({KIND_TAG: JOB_KIND, "mode": mode, "direction": direction, "variant": variant,
                         "seed": str(seed), "paper_row": variants.PAPER_ROWS[variant], **(job_tags or {})})
        tags = {}
        if variant != "dfs":
            finetune = self._run({KIND_TAG: STEP_KIND, STEP_TAG: "finetune"}, job)
            self._history(finetune, "loss", loss or [(10, 2.0), (20, 1.0), (30, 0.5)])
            self.client.set_terminated(finetune)
            tags[step_run_tag("finetune")] = finetune
        if eval_run is None:
            eval_run = self._run({KIND_TAG: STEP_KIND, STEP_TAG: "eval"}, job)
            if artifact:
                folder = self.tmp / eval_run
                folder.mkdir()
                path = folder / EPISODES_ARTIFACT
                path.write_text("".join(json.dumps(e) + "\n"
                                        for e in episodes(mode, wins, variant == "dfs")))
                self.client.log_artifact(eval_run, str(path))
            if curve:
                self._history(eval_run, CURVE_METRIC, curve)
            self.client.set_terminated(eval_run)
        tags[step_run_tag("eval")] = eval_run
        for key, value in tags.items():
            self.client.set_tag(job, key, value)
        self.client.set_terminated(job, status)
        return job, eval_run


def cell(table, mode, direction, variant, subset="all"):
    """The one row of a long success table for this cell and subset."""
    rows = table[(table["mode"] == mode) & (table["direction"] == direction)
                 & (table["variant"] == variant) & (table["subset"] == subset)]
    assert len(rows) == 1
    return rows.iloc[0]
