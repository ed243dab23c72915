"""The MLflow layout every step writes and the report reads: one place for tag, metric and artifact names.

Layout of an experiment:

- a **job run** per (direction, variant, mode, seed), tagged ``cogmap.kind=job`` plus ``direction``,
  ``variant``, ``mode``, ``seed``, ``paper_row`` and the ids of the step runs it used
  (``cogmap.run.data-build``, ``cogmap.run.finetune``, ``cogmap.run.eval``; a reused step points at the
  run that first produced it);
- **step runs** nested under the job that first ran them, tagged ``cogmap.kind=step``, ``cogmap.step``
  and ``cogmap.hash`` (the hash of everything that decides the step's output).

The eval run logs the metrics in ``EVAL_METRICS`` and the artifact ``episodes.jsonl`` (one record per test
world: `pipeline.core.episodes.ScoredEpisode`); with a checkpoint curve it also logs ``curve_success_rate`` with
``step`` = the checkpoint's training step, and each checkpoint's episodes as ``curve/step-<n>.jsonl``. The
finetune run holds transformers' training metrics (``loss`` by step), the model under ``model/`` with its
tokenizer, and an MLflow logged model. Data-build, finetune and eval runs log the conversations they use as
MLflow dataset inputs. The experiment is tagged ``mlflow.experimentKind=custom_model_development``.
"""

from __future__ import annotations

import fcntl
import hashlib
import warnings
from contextlib import contextmanager, nullcontext
from pathlib import Path
from typing import Iterator

KIND_TAG = "cogmap.kind"
STEP_TAG = "cogmap.step"
HASH_TAG = "cogmap.hash"
JOB_KIND, STEP_KIND, REPORT_KIND = "job", "step", "report"
# Job-run tags: the largest train world sides (data.train_size_x/y). Test worlds within both are interpolated;
# the report draws this box on the size heatmaps.
TRAIN_MAX_TAGS = ("train_max_x", "train_max_y")


def step_run_tag(step: str) -> str:
    """The job-run tag that holds the id of the run that produced ``step``."""
    return f"cogmap.run.{step}"


EPISODES_ARTIFACT = "episodes.jsonl"
VALID_EPISODES_ARTIFACT = "episodes_valid.jsonl"   # eval run: the validation split's episodes (eval.n_valid)
VALID_PREFIX = "valid_"                            # the validation split's metrics: valid_success_rate, ...
CURVE_METRIC = "curve_success_rate"
CURVE_EPISODES_ARTIFACT = "curve"   # eval run: curve/step-<n>.jsonl, the episodes of each checkpoint
CHECKPOINTS_ARTIFACT = "checkpoints"  # finetune run: checkpoints/step-<n>/ loadable model dirs (Figure 3)

def default_tracking_uri(root: str = "outputs") -> str:
    """An absolute SQLite URI under ``root`` (a relative URI or ./mlruns would follow the working directory)."""
    return f"sqlite:///{(Path(root).resolve() / 'mlflow.db').as_posix()}"


class StoreError(RuntimeError):
    """A tracking store that cannot be used: unreachable server, unwritable folder, deleted experiment."""


def _check_writable(folder: str | Path, what: str) -> None:
    """Create ``folder`` if needed and write a probe file in it; StoreError naming it if that fails."""
    import tempfile

    path = Path(folder).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".write-probe-"):
            pass
    except OSError as error:
        raise StoreError(f"{what} {str(path)!r} is not a writable folder ({type(error).__name__}: {error}); "
                         f"choose a tracking.root you can write to") from None


def check_store(tracking_uri: str, artifact_root: str | None = None, timeout: float = 5.0) -> None:
    """Fail fast on a store that cannot work, before any job starts.

    A sqlite store's folder (and the artifact root) must be writable; an http(s) server must answer
    within ``timeout`` seconds (MLflow itself retries a dead server for minutes before it gives up).
    """
    import urllib.error
    import urllib.request
    from urllib.parse import urlparse

    scheme = urlparse(tracking_uri).scheme
    if scheme == "sqlite":
        database = _sqlite_path(tracking_uri)
        if database is not None:
            _check_writable(database.parent, "the MLflow store's folder")
    elif scheme in ("http", "https"):
        try:
            urllib.request.urlopen(f"{tracking_uri.rstrip('/')}/health", timeout=timeout).close()
        except urllib.error.HTTPError:
            pass  # the server answered (an error status still means it is there)
        except (urllib.error.URLError, OSError, ValueError) as error:
            reason = getattr(error, "reason", error)
            raise StoreError(
                f"tracking URI {tracking_uri!r} did not answer within {timeout:g} s ({reason}); start the server "
                f"(`mlflow server --host 127.0.0.1 --port PORT`) or use a local sqlite:/// URI"
            ) from None
    if artifact_root:
        _check_writable(artifact_root, "the artifact folder")


def ensure_experiment(tracking_uri: str, name: str, artifact_root: str) -> str:
    """Create the store and the experiment once (with artifacts under ``artifact_root``); return its id.

    Processes opening a new, empty SQLite store at once crash in MLflow's migrations ("table ... already
    exists"), so a SQLite store is created under a file lock beside the database: two commands started
    together on a new store both go on. A store that cannot work (see `check_store`) or an experiment that
    was deleted raises StoreError first. The experiment is tagged as model training, so MLflow's UI shows
    its runs rather than its GenAI pages.
    """
    check_store(tracking_uri, artifact_root)
    database = _sqlite_path(tracking_uri)
    with file_lock(Path(str(database) + ".lock")) if database else nullcontext():
        return _ensure_experiment(tracking_uri, name, artifact_root)


def _sqlite_path(tracking_uri: str) -> Path | None:
    if not tracking_uri.startswith("sqlite:///"):
        return None
    database = tracking_uri[len("sqlite:///"):]
    return Path(database) if database and database != ":memory:" else None


@contextmanager
def file_lock(path: Path) -> Iterator[None]:
    """An exclusive advisory lock, released by the kernel even if the holder is killed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def _ensure_experiment(tracking_uri: str, name: str, artifact_root: str) -> str:
    import mlflow

    mlflow.set_tracking_uri(tracking_uri)
    experiment = mlflow.get_experiment_by_name(name)
    if experiment is not None:
        if experiment.lifecycle_stage == "deleted":
            raise StoreError(
                f"experiment {name!r} in {tracking_uri} is deleted; restore it (`mlflow experiments restore "
                f"--experiment-id {experiment.experiment_id}`) or choose another tracking.experiment"
            )
        if experiment.tags.get(EXPERIMENT_KIND_TAG) != EXPERIMENT_KIND:
            mlflow.MlflowClient(tracking_uri).set_experiment_tag(experiment.experiment_id, EXPERIMENT_KIND_TAG,
                                                                 EXPERIMENT_KIND)
        return experiment.experiment_id
    location = Path(artifact_root).resolve()
    location.mkdir(parents=True, exist_ok=True)
    return mlflow.create_experiment(name, artifact_location=location.as_uri(),
                                    tags={EXPERIMENT_KIND_TAG: EXPERIMENT_KIND})


# MLflow's UI classifies an experiment by this tag, and opens a run or experiment page on its model-training
# view (runs, models, datasets) when the URL says workflowType=machine_learning.
EXPERIMENT_KIND_TAG, EXPERIMENT_KIND = "mlflow.experimentKind", "custom_model_development"
UI_VIEW = "workflowType=machine_learning"


def ui_path(experiment_id: str, run_id: str | None = None) -> str:
    """The path (after the UI's address) of an experiment or run page in MLflow's model-training view."""
    run = f"/runs/{run_id}" if run_id else "/runs"
    return f"#/experiments/{experiment_id}{run}?{UI_VIEW}"


def log_settings(values: dict, prefix: str) -> None:
    """Log a settings section as the active run's params, flattened (``train.learning_rate``, ...)."""
    import mlflow

    mlflow.log_params({f"{prefix}.{key}": value for key, value in _flatten(values)})


def _flatten(tree, prefix: str = ""):
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _flatten(value, f"{prefix}.{key}" if prefix else str(key))
    else:
        yield prefix, tree


def log_dataset(uri: str, local: Path, name: str, context: str) -> None:
    """Log a conversations file as an MLflow dataset input of the active run (source and digest), so the
    runs table's Dataset column and the lineage show which data a run used."""
    import mlflow
    from mlflow.data.dataset_source_registry import resolve_dataset_source
    from mlflow.data.meta_dataset import MetaDataset

    digest = hashlib.sha256(Path(local).read_bytes()).hexdigest()[:16]
    with warnings.catch_warnings():
        # MLflow registers the same local-file source class for the "" and "file" schemes and warns that a
        # file:// URI matches both; they are one and the same.
        warnings.filterwarnings("ignore", message="The specified dataset source can be interpreted in multiple ways")
        source = resolve_dataset_source(uri)
    mlflow.log_input(MetaDataset(source, name=name, digest=digest), context=context)
