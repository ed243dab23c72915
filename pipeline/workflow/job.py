"""The job behind `python -m pipeline.run`: one job = data-build -> finetune -> eval, each a (reusable) MLflow step run
nested under the job's run. With `-m`, Hydra sweeps the config groups into several jobs."""

from __future__ import annotations

import logging
import os
import signal
import sys
from contextlib import contextmanager
from dataclasses import asdict, fields
from pathlib import Path

import mlflow
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pipeline.core.variants import PAPER_ROWS
from pipeline.core.checks import SettingError
from pipeline.core.world import WorldError
from pipeline.lm.model_settings import ModelKind
from pipeline.lm.training.beside import end_early
from pipeline.workflow.config import ConfigError, JobSettings, UndefinedCell, config_hash, register_configs, validate
from pipeline.workflow.data_build import TEST_CONVERSATIONS, TRAIN_CONVERSATIONS, TextSettings, log_step_dataset, run_data_build
from pipeline.workflow.evaluation import run_eval
from pipeline.workflow.finetune import run_finetune_step
from pipeline.workflow.steps import StepRun, clear_inherited_run, get_or_run
from pipeline.workflow.tracking import (
    JOB_KIND, KIND_TAG, TRAIN_MAX_TAGS, VALID_PREFIX, StoreError, check_store, ensure_experiment, step_run_tag, ui_path,
)

log = logging.getLogger("pipeline.run")

# Where the README's `mlflow ui` command serves the store.
UI_ADDRESS = "http://127.0.0.1:5000"
# Bumped when a step's code changes what it writes, so old runs are not reused for new semantics.
STEP_VERSIONS = {"data-build": 2, "finetune": 3, "eval": 3}   # README, "Step versions", says what each bump changed
# The same for a pretrained model's (kind=hf) finetune alone: its subword tokenizer gives other ids since each
# human turn is encoded with its prefix as one text (issue 24); a scratch model's word-level ids did not change.
HF_FINETUNE_VERSION = 2

register_configs()
# Our own bars (data-build, training, eval) say what is happening; per-file download bars only add noise.
os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")


def _artifact_root(cfg: DictConfig) -> str:
    return str(Path(cfg.tracking.root) / "mlartifacts")


def prepare_store(cfg: DictConfig) -> str:
    """Create the SQLite store and the experiment (idempotent); return the experiment id."""
    try:
        return ensure_experiment(cfg.tracking.uri, cfg.tracking.experiment, _artifact_root(cfg))
    except Exception as error:  # the store is the first thing touched: say which one failed
        raise ConfigError(f"cannot open the MLflow store tracking.uri={cfg.tracking.uri!r}: {error}") from error


class PrepareStore(Callback):
    """Creates the store once in the parent process, before parallel jobs could race on a new database."""

    def on_multirun_start(self, config: DictConfig, **kwargs) -> None:
        prepare_store(config)

    def on_run_start(self, config: DictConfig, **kwargs) -> None:
        # Before Hydra makes its run folder under tracking.root: an unusable store is named, not a raw mkdir.
        with errors_for_people():
            try:
                check_store(config.tracking.uri, _artifact_root(config))
            except StoreError as error:
                raise ConfigError(f"tracking.root={config.tracking.root!r}, tracking.uri={config.tracking.uri!r}: "
                                  f"{error}") from None


# ---------------------------------------------------------------------------------------------------- hashes
def job_texts(cfg: DictConfig, job: JobSettings) -> TextSettings:
    """What decides the job's texts besides its worlds (its direction, variant and mode; the model's prompt,
    step headers, numbers, Plan form, newlines and spaces)."""
    return TextSettings.of(str(cfg.direction.value), job.variant, str(cfg.mode.value), seed=job.data.seed,
                           prompt=job.model.prompt, step_headers=job.model.step_headers, numbers=job.model.numbers,
                           plan_form=job.model.plan_form, newlines=job.model.newlines, spaces=job.model.spaces)


def step_hashes(job: JobSettings, seed: int, texts: TextSettings) -> dict[str, str]:
    """The identity of each step: what decides its output, and its inputs' identities."""
    digests = [None if found is None else found.sha256 for found in (job.files["test"], job.files["train"])]
    data = config_hash("data-build", STEP_VERSIONS["data-build"], hashed(job.data, asdict(job.data)),
                       hashed(texts, asdict(texts)), *digests)
    hf = [f"hf {HF_FINETUNE_VERSION}"] if job.model.kind is ModelKind.hf else []
    finetune = config_hash("finetune", STEP_VERSIONS["finetune"], hashed(job.model, job.model.to_dict()),
                           hashed(job.train, job.train.to_dict()), seed, data, *hf)
    evaluation = config_hash("eval", STEP_VERSIONS["eval"], hashed(job.eval, asdict(job.eval)), finetune, data)
    return {"data-build": data, "finetune": finetune, "eval": evaluation}


def hashed(settings, values: dict) -> dict:
    """A section's values as its step's hash takes them: a field added after its step's version, whose
    default keeps the old behaviour (``metadata={"hash_if_set": True}``), counts only when set, so adding it
    does not make every finished step look new."""
    return {key: value for key, value in values.items()
            if not any(f.name == key and f.metadata.get("hash_if_set") and value == f.default for f in fields(settings))}


# ---------------------------------------------------------------------------------------------------- job
def run_job(cfg: DictConfig) -> dict | None:
    """Run (or reuse) the job's three steps; return the eval metrics (None for a skipped grid cell)."""
    try:
        job = validate(cfg)
    except UndefinedCell as error:
        if cfg.skip_undefined:
            log.info("skipped (undefined in the paper's grid): %s", error)
            return None
        raise
    direction, mode, variant = str(cfg.direction.value), str(cfg.mode.value), job.variant
    texts = job_texts(cfg, job)
    hashes = step_hashes(job, cfg.seed, texts)
    clear_inherited_run()
    from transformers.utils import logging as hf_logging

    hf_logging.disable_progress_bar()
    if cfg.threads:
        import torch

        torch.set_num_threads(cfg.threads)
    if job.train.torch_compile.blocks:
        from pipeline.lm.training.compile import compile_beside

        compile_beside(job.model, job.train, job.data.frame)  # the layer compiled beside the data-build
    else:
        end_early()  # the process the command line started: nothing to compile
    experiment_id = prepare_store(cfg)
    mlflow.set_tracking_uri(cfg.tracking.uri)
    mlflow.set_experiment(experiment_id=experiment_id)
    tags = {"direction": direction, "variant": variant, "mode": mode, "seed": str(cfg.seed),
            "paper_row": PAPER_ROWS[variant]}
    work_dir = Path(cfg.work_dir)
    train_max = dict(zip(TRAIN_MAX_TAGS, map(str, job.data.train_max)))
    with mlflow.start_run(run_name=f"{direction}-{variant}-{mode}", tags={**tags, **train_max, KIND_TAG: JOB_KIND}) as run:
        mlflow.log_dict(OmegaConf.to_container(cfg, resolve=True, enum_to_str=True), "config.json")

        def step(name: str, body) -> StepRun:
            done = get_or_run(name, hashes[name], experiment_id=experiment_id, work_dir=work_dir, tags=tags, body=body)
            mlflow.set_tag(step_run_tag(name), done.run_id)
            log.info("%s: %s run %s", name, "reused" if done.reused else "ran", done.run_id)
            return done

        data = step("data-build", lambda d: run_data_build(job.data, texts, job.files, d))
        # The job's own row in the runs table names its data too (the step runs below it hold the same).
        log_step_dataset(data, texts, TRAIN_CONVERSATIONS, "train", "training")
        log_step_dataset(data, texts, TEST_CONVERSATIONS, "test", "evaluation")
        finetune = step("finetune", lambda d: run_finetune_step(job.model, job.train, cfg.seed, job.data.frame, texts,
                                                               data, d))
        if job.train.torch_compile.blocks:
            from pipeline.lm.training.compile import stop_beside

            stop_beside()  # a reused training needs no compiled layer
        evaluation = step("eval", lambda d: run_eval(job.eval, job.model, texts, data, finetune, d, job.data))
        results = mlflow.get_run(evaluation.run_id).data.metrics
        mlflow.log_metrics({key: value for key, value in results.items() if key != "step_seconds"})
    reused = [s.step for s in (data, finetune, evaluation) if s.reused]
    valid = f" | validation {_rates(results, VALID_PREFIX)}" if f"{VALID_PREFIX}n_episodes" in results else ""
    print(
        f"[job] {direction} {variant} {mode}: success {_rates(results)}{valid} | reused: {', '.join(reused) or 'nothing'} "
        f"| job run {run.info.run_id}\n"
        f"      in `mlflow ui` (README): {UI_ADDRESS}/{ui_path(experiment_id, run.info.run_id)}",
        flush=True,
    )
    return results


def _rate(results: dict, key: str) -> str:
    return f"{results[key]:.3f}" if key in results else "n/a (0 worlds)"


def _rates(results: dict, prefix: str = "") -> str:
    """`0.305 (interp 0.817, extrap 0.086) over 200 worlds`; a split with no worlds reads `n/a`."""
    return (f"{_rate(results, prefix + 'success_rate')} (interp {_rate(results, prefix + 'success_rate_interp')}, "
            f"extrap {_rate(results, prefix + 'success_rate_extrap')}) over "
            f"{int(results.get(prefix + 'n_episodes', 0))} worlds")


@contextmanager
def errors_for_people():
    """A configuration or input error ends a single run with one line on stderr (``error: ...``) and exit
    status 2, without a traceback; ``HYDRA_FULL_ERROR=1`` shows the traceback. In a multirun the error is
    raised as usual, so the sweep records the failed job and goes on."""
    try:
        yield
    except (ConfigError, WorldError, SettingError) as error:
        if os.environ.get("HYDRA_FULL_ERROR") == "1" or _multirun():
            raise
        print(f"error: {error}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None


def _multirun() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def _interrupt(signum, frame) -> None:
    # A stopped job (SIGTERM from a shell, or from SLURM without submitit) unwinds like Ctrl-C, so its MLflow runs
    # end FAILED/KILLED.
    raise KeyboardInterrupt(f"signal {signum}")


def main(cfg: DictConfig) -> float | None:
    """The Hydra task (`pipeline.run` decorates it); returns the success rate (what a sweeper would optimise)."""
    # Under submitit (hydra/launcher=slurm or local_submitit) SIGTERM is left to submitit, which ignores it:
    # SLURM's preemption sends SIGTERM before submitit's own signal, on which submitit requeues the job.
    if not os.environ.get("SUBMITIT_EXECUTOR"):
        signal.signal(signal.SIGTERM, _interrupt)
    with errors_for_people():
        results = run_job(cfg)
    return None if results is None else results.get("success_rate")
