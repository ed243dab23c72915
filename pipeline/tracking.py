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


def ensure_experiment(tracking_uri: str, name: str, artifact_root: str) -> str:
    """Create the store and the experiment once (with artifacts under ``artifact_root``); return its id.

    Called before any job starts: parallel jobs opening a new, empty SQLite store at once crash.
    """
    from pathlib import Path

    import mlflow

    mlflow.set_tracking_uri(tracking_uri)
    experiment = mlflow.get_experiment_by_name(name)
    if experiment is not None:
        return experiment.experiment_id
    location = Path(artifact_root).resolve()
    location.mkdir(parents=True, exist_ok=True)
    return mlflow.create_experiment(name, artifact_location=location.as_uri())
