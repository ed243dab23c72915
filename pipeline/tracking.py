"""The MLflow layout every step writes and the report reads: one place for tag, metric and artifact names.

Layout of an experiment:

- a **job run** per (direction, variant, mode, seed), tagged ``cogmap.kind=job`` plus ``direction``,
  ``variant``, ``mode``, ``seed``, ``paper_row`` and the ids of the step runs it used
  (``cogmap.run.data-build``, ``cogmap.run.finetune``, ``cogmap.run.eval``; a reused step points at the
  run that first produced it);
- **step runs** nested under the job that first ran them, tagged ``cogmap.kind=step``, ``cogmap.step``
  and ``cogmap.hash`` (the hash of everything that decides the step's output).

The eval run logs the metrics in ``EVAL_METRICS`` and the artifact ``episodes.jsonl`` (one record per test
world, fields ``EPISODE_FIELDS``); with a checkpoint curve it also logs ``curve_success_rate`` with
``step`` = the checkpoint's training step. The finetune run holds transformers' training metrics
(``loss`` by step), the model under ``model/`` and its tokenizer.
"""

from __future__ import annotations

KIND_TAG = "cogmap.kind"
STEP_TAG = "cogmap.step"
HASH_TAG = "cogmap.hash"
JOB_KIND, STEP_KIND, REPORT_KIND = "job", "step", "report"
STEPS = ("data-build", "finetune", "eval")
JOB_TAGS = ("direction", "variant", "mode", "seed", "paper_row")
# Job-run tags: the largest train world sides (data.train_size_x/y). Test worlds within both are interpolated;
# the report draws this box on the size heatmaps.
TRAIN_MAX_TAGS = ("train_max_x", "train_max_y")


def step_run_tag(step: str) -> str:
    """The job-run tag that holds the id of the run that produced ``step``."""
    return f"cogmap.run.{step}"


EPISODES_ARTIFACT = "episodes.jsonl"
CURVE_METRIC = "curve_success_rate"
CHECKPOINTS_ARTIFACT = "checkpoints"  # finetune run: checkpoints/step-<n>/ loadable model dirs (Figure 3)

# Per-episode record fields (eval's episodes.jsonl). Optimal-setting-only fields are null in reachable.
EPISODE_FIELDS = (
    "world_index",      # index in the test split
    "size_x", "size_y", "optimal_length", "dead_ends", "up_right_only", "interpolated",
    "success",          # bool: SUCCESS in either setting
    "outcome",          # reachable: success|deadend|max_step|invalid; optimal: success|fail; error: error
    "n_moves",          # moves taken (reachable) or planned (optimal)
    "moves",            # list of move words
    "parsed", "valid", "reaches_goal", "map_exact", "map_first_error",  # optimal setting, graded
    "error",            # null, or why this single episode could not run (e.g. prompt longer than context)
)

EVAL_METRICS = (
    "success_rate", "success_rate_interp", "success_rate_extrap", "n_episodes",
    "rate_deadend", "rate_max_step", "rate_invalid", "rate_error",      # reachable outcomes
    "rate_parsed", "rate_valid", "rate_reaches_goal", "rate_map_exact",  # optimal, graded
)

# The paper's row names (SPEC 3 and 5), used as the ``paper_row`` tag and in the report's tables.
PAPER_ROWS = {
    "marking-deadend": "MARKING deadend",
    "no-marking": "w.o. MARKING",
    "no-backtrack": "w.o. BACKTRACK",
    "no-marking-no-backtrack": "w.o. MARKING BACKTRACK",
    "no-all": "w.o. ALL",
    "no-all-no-backtrack": "w.o. ALL BACKTRACK",
    "none": "NONE",
    "cot": "CoT",
    "dfs": "DFS exploration",
}


def default_tracking_uri(root: str = "outputs") -> str:
    """An absolute SQLite URI under ``root`` (a relative URI or ./mlruns would follow the working directory)."""
    from pathlib import Path

    return f"sqlite:///{(Path(root).resolve() / 'mlflow.db').as_posix()}"


class StoreError(RuntimeError):
    """A tracking store that cannot be used: unreachable server, unwritable folder, deleted experiment."""


def _check_writable(folder: "str | Path", what: str) -> None:
    """Create ``folder`` if needed and write a probe file in it; StoreError naming it if that fails."""
    import tempfile
    from pathlib import Path

    path = Path(folder).expanduser()
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path, prefix=".write-probe-"):
            pass
    except OSError as error:
        raise StoreError(f"{what} {str(path)!r} is not a writable folder ({type(error).__name__}: {error}); "
                         f"choose a tracking.root you can write to") from None


def check_store(tracking_uri: str, artifact_root: "str | None" = None, timeout: float = 5.0) -> None:
    """Fail fast on a store that cannot work, before any job starts.

    A sqlite store's folder (and the artifact root) must be writable; an http(s) server must answer
    within ``timeout`` seconds (MLflow itself retries a dead server for minutes before it gives up).
    """
    import urllib.error
    import urllib.request
    from pathlib import Path
    from urllib.parse import urlparse

    scheme = urlparse(tracking_uri).scheme
    if scheme == "sqlite":
        database = tracking_uri[len("sqlite:///"):] if tracking_uri.startswith("sqlite:///") else ""
        if database and database != ":memory:":
            _check_writable(Path(database).parent, "the MLflow store's folder")
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

    Called before any job starts: parallel jobs opening a new, empty SQLite store at once crash. A store
    that cannot work (see `check_store`) or an experiment that was deleted raises StoreError first.
    """
    from pathlib import Path

    import mlflow

    check_store(tracking_uri, artifact_root)
    mlflow.set_tracking_uri(tracking_uri)
    experiment = mlflow.get_experiment_by_name(name)
    if experiment is not None:
        if experiment.lifecycle_stage == "deleted":
            raise StoreError(
                f"experiment {name!r} in {tracking_uri} is deleted; restore it (`mlflow experiments restore "
                f"--experiment-id {experiment.experiment_id}`) or choose another tracking.experiment"
            )
        return experiment.experiment_id
    location = Path(artifact_root).resolve()
    location.mkdir(parents=True, exist_ok=True)
    return mlflow.create_experiment(name, artifact_location=location.as_uri())
