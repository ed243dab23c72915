"""Steps that remember: a step is identified by a hash of what decides its output; a FINISHED MLflow run
with that hash is reused instead of run again.

A per-hash file lock makes this exact under parallel jobs: the holder either finds the finished run or
runs the step, and any RUNNING run with the same hash that it finds belonged to a process that died
(killed jobs release their locks), so it is marked KILLED rather than left looking alive, and so is the
job run it was nested under (same process, same death). A FINISHED run whose artifacts have gone missing
from the artifact store, or changed since the step wrote them (each step records the SHA-256 of every file
it logged), is not reused: the step runs again, and says why in one line. Each step gets
a stable working folder (``<work_dir>/<step>/<hash>``) for checkpoints and partial records, so a rerun
of an interrupted step resumes instead of starting over.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable
from urllib.parse import unquote, urlparse

import mlflow
from mlflow.entities import RunStatus

from pipeline.workflow.tracking import HASH_TAG, KIND_TAG, STEP_KIND, STEP_TAG, file_lock

NOTE_TAG = "cogmap.note"
# The SHA-256 of every file a step logged, written as the run's last artifact; a reuse checks them.
MANIFEST = "cogmap_manifest.json"
# How many top-level artifacts the step logged; a reused run must still have some if it had any.
ARTIFACTS_TAG = "cogmap.n_artifacts"
_PARENT_TAG = "mlflow.parentRunId"


class StepArtifactError(RuntimeError):
    """A finished step's artifact that cannot be read back."""


@dataclass(frozen=True)
class StepRun:
    """A finished step: the run that produced it, and whether this job reused it."""

    step: str
    run_id: str
    hash: str
    reused: bool

    def artifact(self, path: str) -> str:
        """A local path to one of the run's artifacts (downloaded if the store is remote)."""
        try:
            return mlflow.artifacts.download_artifacts(run_id=self.run_id, artifact_path=path)
        except Exception as error:
            raise StepArtifactError(
                f"{self.step} run {self.run_id} (hash {self.hash}) has no readable artifact {path!r}: {error}. "
                f"Delete that run (`mlflow runs delete --run-id {self.run_id}`) so the step is built again."
            ) from error


def _runs_with_hash(experiment_id: str, step: str, step_hash: str, status: str) -> list:
    query = f"tags.`{STEP_TAG}` = '{step}' and tags.`{HASH_TAG}` = '{step_hash}' and attributes.status = '{status}'"
    return mlflow.search_runs(
        experiment_ids=[experiment_id], filter_string=query, order_by=["attributes.start_time DESC"],
        output_format="list",
    )


def _artifacts_present(run) -> bool:
    """Whether a finished run still has the artifacts it logged (older runs without the tag: assumed)."""
    expected = run.data.tags.get(ARTIFACTS_TAG)
    if not expected or expected == "0":
        return True
    try:
        return bool(mlflow.MlflowClient().list_artifacts(run.info.run_id))
    except Exception:
        return False


def _local_artifacts(run) -> Path | None:
    """The run's artifact folder when the artifact store is this file system (None for a remote store)."""
    parsed = urlparse(run.info.artifact_uri)
    return Path(unquote(parsed.path)) if parsed.scheme in ("", "file") else None


def _sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def artifact_manifest(folder: Path) -> dict[str, str]:
    """Relative path -> SHA-256 of every file under ``folder`` but the manifest itself, in path order."""
    files = sorted(p for p in folder.rglob("*") if p.is_file() and p.name != MANIFEST)
    return {p.relative_to(folder).as_posix(): _sha256(p) for p in files}


def changed_artifacts(run) -> str | None:
    """Why a finished run's artifacts can no longer be trusted (a file missing, added or changed since the
    step wrote its manifest), or None. Runs without a manifest, or on a remote store, are checked only for
    being there at all."""
    folder = _local_artifacts(run)
    if folder is None or not (folder / MANIFEST).is_file():
        return None if _artifacts_present(run) else "its artifacts are missing from the store"
    try:
        recorded = json.loads((folder / MANIFEST).read_text())
    except (OSError, ValueError) as error:
        return f"its artifact manifest is unreadable ({error})"
    now = artifact_manifest(folder) if folder.is_dir() else {}
    for name, digest in recorded.items():
        if name not in now:
            return f"its artifact {name} is missing"
        if now[name] != digest:
            return f"its artifact {name} changed since the step finished (SHA-256 {now[name][:12]}, recorded {digest[:12]})"
    return None


def find_finished(experiment_id: str, step: str, step_hash: str) -> str | None:
    """The id of the latest FINISHED run of ``step`` with ``step_hash`` whose artifacts are all there and
    unchanged; a run that fails the check is noted in the store and on stdout, and not reused."""
    for run in _runs_with_hash(experiment_id, step, step_hash, "FINISHED"):
        reason = changed_artifacts(run)
        if reason is None:
            return run.info.run_id
        mlflow.MlflowClient().set_tag(run.info.run_id, NOTE_TAG, f"not reused: {reason}")
        print(f"[{step}] not reusing run {run.info.run_id}: {reason}; running the step again", flush=True)
    return None


def _mark_stale_runs_killed(experiment_id: str, step: str, step_hash: str) -> None:
    """Mark RUNNING runs with this hash KILLED (their process died: we hold the lock they held), and
    their job runs too: a job dies with its step, and would otherwise stay RUNNING for ever."""
    client = mlflow.MlflowClient()
    active = mlflow.active_run()
    current = active.info.run_id if active else None
    note = "interrupted: its process ended without finishing"
    for run in _runs_with_hash(experiment_id, step, step_hash, "RUNNING"):
        client.set_tag(run.info.run_id, NOTE_TAG, note)
        client.set_terminated(run.info.run_id, status=RunStatus.to_string(RunStatus.KILLED))
        parent = run.data.tags.get(_PARENT_TAG)
        if parent and parent != current:
            try:
                if client.get_run(parent).info.status == "RUNNING":
                    client.set_tag(parent, NOTE_TAG, f"interrupted during its {step} step")
                    client.set_terminated(parent, status=RunStatus.to_string(RunStatus.KILLED))
            except Exception:  # a parent deleted from the store: nothing to mark
                pass


def get_or_run(
    step: str,
    step_hash: str,
    *,
    experiment_id: str,
    work_dir: str | Path,
    tags: dict[str, str],
    body: Callable[[Path], None],
) -> StepRun:
    """Reuse the FINISHED run of ``step`` with ``step_hash``, or run ``body(step_dir)`` in a new nested run.

    ``body`` logs its own params, metrics and artifacts into the active run; an exception marks the run
    FAILED and propagates.
    """
    step_dir = Path(work_dir) / step / step_hash
    with file_lock(Path(work_dir) / "locks" / f"{step}-{step_hash}.lock"):
        found = find_finished(experiment_id, step, step_hash)
        if found:
            return StepRun(step, found, step_hash, reused=True)
        _mark_stale_runs_killed(experiment_id, step, step_hash)
        step_dir.mkdir(parents=True, exist_ok=True)
        run_tags = {**tags, KIND_TAG: STEP_KIND, STEP_TAG: step, HASH_TAG: step_hash}
        with mlflow.start_run(run_name=step, nested=True, tags=run_tags) as run:
            started = time.perf_counter()
            body(step_dir)
            mlflow.log_metric("step_seconds", time.perf_counter() - started)
            mlflow.set_tag(ARTIFACTS_TAG, str(len(mlflow.MlflowClient().list_artifacts(run.info.run_id))))
            _write_manifest(mlflow.get_run(run.info.run_id), step_dir)
        return StepRun(step, run.info.run_id, step_hash, reused=False)


def _write_manifest(run, step_dir: Path) -> None:
    folder = _local_artifacts(run)
    if folder is None or not folder.is_dir():
        return  # a remote artifact store keeps its own checksums
    target = step_dir / MANIFEST
    target.write_text(json.dumps(artifact_manifest(folder), indent=1, sort_keys=True) + "\n")
    mlflow.log_artifact(str(target))


def clear_inherited_run() -> None:
    """Forget a run id left in the environment, which would make every start_run resume that run."""
    os.environ.pop("MLFLOW_RUN_ID", None)
