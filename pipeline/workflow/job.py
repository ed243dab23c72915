"""`python -m pipeline.run`: one job = data-build -> finetune -> eval, each a (reusable) MLflow step run
nested under the job's run. With `-m`, Hydra sweeps the config groups into several jobs."""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import signal
import sys
import warnings
from contextlib import contextmanager
from dataclasses import asdict
from pathlib import Path

import mlflow
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from pipeline.workflow.config import ConfigError, UndefinedCell, config_hash, register_configs, validate
from pipeline.workflow.data_build import (
    TEST_CONVERSATIONS, TEST_STATS, TEST_WORLDS, TRAIN_CONVERSATIONS, TextSpec, build_splits, read_conversations,
    write_dataset,
)
from pipeline.core.world import WorldError
from pipeline.workflow.steps import StepRun, clear_inherited_run, get_or_run
from pipeline.workflow.tracking import StoreError, check_store, ui_path
from pipeline.workflow.tracking import CHECKPOINTS_ARTIFACT, CURVE_EPISODES_ARTIFACT, CURVE_METRIC, EPISODES_ARTIFACT, JOB_KIND, KIND_TAG, PAPER_ROWS, TRAIN_MAX_TAGS, ensure_experiment, step_run_tag

log = logging.getLogger("pipeline.run")

# Where the README's `mlflow ui` command serves the store.
UI_ADDRESS = "http://127.0.0.1:5000"
# Bumped when a step's code changes what it writes, so old runs are not reused for new semantics.
STEP_VERSIONS = {"data-build": 1, "finetune": 1, "eval": 2}   # eval 2: records keep the answers

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
def _file_digest(path: str | None) -> str | None:
    return hashlib.sha256(Path(path).expanduser().read_bytes()).hexdigest() if path else None


def step_hashes(cfg: DictConfig, spec: TextSpec) -> dict[str, str]:
    """The identity of each step: what decides its output, and its inputs' identities."""
    data = config_hash("data-build", STEP_VERSIONS["data-build"], cfg.data, asdict(spec), _file_digest(cfg.data.test_file))
    finetune = config_hash("finetune", STEP_VERSIONS["finetune"], cfg.model, cfg.train, cfg.seed, data)
    evaluation = config_hash("eval", STEP_VERSIONS["eval"], cfg.eval, finetune, data)
    return {"data-build": data, "finetune": finetune, "eval": evaluation}


# ---------------------------------------------------------------------------------------------------- steps
def _log_config(node: DictConfig, prefix: str) -> None:
    flat = {f"{prefix}.{k}": v for k, v in _flatten(OmegaConf.to_container(node, resolve=True, enum_to_str=True))}
    mlflow.log_params(flat)


def _flatten(tree, prefix: str = ""):
    if isinstance(tree, dict):
        for key, value in tree.items():
            yield from _flatten(value, f"{prefix}.{key}" if prefix else str(key))
    else:
        yield prefix, tree


def _train_max(cfg: DictConfig) -> tuple[int, int]:
    """The largest train world sides (X, Y): test worlds within both are interpolated."""
    return max(cfg.data.train_size_x), max(cfg.data.train_size_y)


def data_build_body(cfg: DictConfig, spec: TextSpec, step_dir: Path) -> None:
    _log_config(cfg.data, "data")
    train, test = build_splits(cfg.data)
    out = step_dir / "dataset"
    summary = write_dataset(out, train, test, spec, _train_max(cfg))
    mlflow.set_tag("dataset_sha256", summary["sha256"])
    mlflow.log_metrics({
        "n_train": summary["n_train"], "n_test": summary["n_test"],
        "train_tokens_mean": summary["train_tokens"]["mean"], "train_tokens_max": summary["train_tokens"]["max"],
        "test_path_length_mean": summary["test_path_length"]["mean"],
        "test_up_right_only": summary["test_up_right_only"], "test_interpolated": summary["test_interpolated"],
    })
    mlflow.log_artifacts(str(out))
    base = mlflow.get_artifact_uri()
    for artifact, split in ((TRAIN_CONVERSATIONS, "train"), (TEST_CONVERSATIONS, "test")):
        log_dataset(f"{base}/{artifact}", out / artifact, _dataset_name(spec, split), split)


def _dataset_name(spec: TextSpec, split: str) -> str:
    return "-".join(p for p in (spec.direction, spec.variant, spec.mode, split) if p)


def log_dataset(uri: str, local: Path, name: str, context: str) -> None:
    """Log a conversations file as an MLflow dataset input of the active run (source and digest), so the
    runs table's Dataset column and the lineage show which data a run used."""
    from mlflow.data.dataset_source_registry import resolve_dataset_source
    from mlflow.data.meta_dataset import MetaDataset

    digest = hashlib.sha256(Path(local).read_bytes()).hexdigest()[:16]
    with warnings.catch_warnings():
        # MLflow registers the same local-file source class for the "" and "file" schemes and warns that a
        # file:// URI matches both; they are one and the same.
        warnings.filterwarnings("ignore", message="The specified dataset source can be interpreted in multiple ways")
        source = resolve_dataset_source(uri)
    mlflow.log_input(MetaDataset(source, name=name, digest=digest), context=context)


def _log_step_dataset(data: StepRun, spec: TextSpec, artifact: str, split: str, context: str) -> None:
    uri = f"{mlflow.get_run(data.run_id).info.artifact_uri}/{artifact}"
    log_dataset(uri, Path(data.artifact(artifact)), _dataset_name(spec, split), context)


def log_model(cfg: DictConfig, model_dir: str) -> None:
    """The finetuned model as an MLflow logged model: the transformers flavour (weights copied, loadable with
    ``mlflow.transformers.load_model``), or for large models a reference to the run's ``model/`` artifacts."""
    import transformers

    if cfg.model.log_model == "transformers":
        import mlflow.transformers
        import torch

        from pipeline.lm.models import load_model, load_tokenizer

        # From the loaded model, not the folder: MLflow 3.17 cannot read a transformers 5 checkpoint folder
        # (its task table holds class names as strings there).
        model = load_model(model_dir, dtype=cfg.model.dtype, trust_remote_code=cfg.model.trust_remote_code)
        tokenizer = load_tokenizer(model_dir, trust_remote_code=cfg.model.trust_remote_code)
        quiet = logging.getLogger("mlflow.transformers")
        level = quiet.level
        quiet.setLevel(logging.ERROR)  # no model card or licence to look up for a model trained here
        try:
            mlflow.transformers.log_model(
                {"model": model, "tokenizer": tokenizer}, name="model", task="text-generation",
                pip_requirements=[f"torch=={torch.__version__.split('+')[0]}",
                                  f"transformers=={transformers.__version__}"],
            )
        finally:
            quiet.setLevel(level)
    else:
        run_id = mlflow.active_run().info.run_id
        mlflow.create_external_model(name="model", source_run_id=run_id, model_type="transformers",
                                     params={"weights": f"runs:/{run_id}/model"})


def finetune_body(cfg: DictConfig, spec: TextSpec, data: StepRun, step_dir: Path) -> None:
    from pipeline.workflow.finetune import result_metrics, run_finetune

    # Prefixed: transformers' MLflowCallback logs the Trainer's own arguments under their plain names.
    _log_config(cfg.model, "model")
    _log_config(cfg.train, "train")
    train_file = data.artifact(TRAIN_CONVERSATIONS)
    _log_step_dataset(data, spec, TRAIN_CONVERSATIONS, "train", "training")
    result = run_finetune(cfg, read_conversations(train_file), train_file, step_dir)
    mlflow.log_metrics(result_metrics(result))
    mlflow.log_artifacts(result.model_dir, "model")
    log_model(cfg, result.model_dir)
    if cfg.train.log_checkpoints:
        mlflow.log_artifacts(str(_checkpoint_models(step_dir, Path(result.model_dir))), CHECKPOINTS_ARTIFACT)


def _checkpoint_models(step_dir: Path, model_dir: Path) -> Path:
    """Each checkpoint's weights beside the final model's config, tokenizer and chat format: loadable dirs
    ``step-<n>`` (optimizer states stay behind; they are large and only resuming needs them)."""
    out = step_dir / "checkpoint_models"
    shared = [p for p in model_dir.iterdir() if p.is_file() and p.suffix != ".safetensors"]
    for checkpoint in sorted((step_dir / "checkpoints").glob("checkpoint-*")):
        target = out / f"step-{checkpoint.name.split('-')[-1]}"
        target.mkdir(parents=True, exist_ok=True)
        for source in [*shared, *checkpoint.glob("*.safetensors")]:
            shutil.copy2(source, target / source.name)
    return out


def _evaluate_curve(cfg: DictConfig, spec: TextSpec, variant: str, finetune: StepRun, worlds, stats, step_dir: Path) -> None:
    """Figure 3: success of every logged checkpoint on the first ``eval.curve_worlds`` test worlds."""
    from pipeline.workflow.evaluation import evaluate, make_decoder, metrics

    entries = mlflow.artifacts.list_artifacts(run_id=finetune.run_id, artifact_path=CHECKPOINTS_ARTIFACT)
    steps = sorted(int(Path(entry.path).name.split("-")[-1]) for entry in entries if entry.is_dir)
    n = min(cfg.eval.curve_worlds, len(worlds))
    for train_step in steps:
        model_dir = finetune.artifact(f"{CHECKPOINTS_ARTIFACT}/step-{train_step}")
        records = evaluate(
            make_decoder(cfg, model_dir), worlds[:n], stats[:n], mode=spec.mode, direction=spec.direction or "fwd",
            variant=variant, max_steps=cfg.eval.max_steps, partial_path=step_dir / f"curve-{train_step}.partial.jsonl",
            prompt=spec.prompt,
        )
        mlflow.log_metric(CURVE_METRIC, metrics(records)["success_rate"], step=train_step)
        episodes = step_dir / "curve" / f"step-{train_step}.jsonl"
        episodes.parent.mkdir(parents=True, exist_ok=True)
        episodes.write_text("".join(json.dumps(record) + "\n" for record in records))
        mlflow.log_artifact(str(episodes), CURVE_EPISODES_ARTIFACT)


def eval_body(cfg: DictConfig, spec: TextSpec, variant: str, data: StepRun, finetune: StepRun, step_dir: Path) -> None:
    from pipeline.workflow.evaluation import evaluate, make_decoder, metrics
    from pipeline.core.world import load_worlds

    _log_config(cfg.eval, "eval")
    _log_step_dataset(data, spec, TEST_CONVERSATIONS, "test", "evaluation")
    worlds = load_worlds(data.artifact(TEST_WORLDS))
    stats = [json.loads(line) for line in Path(data.artifact(TEST_STATS)).read_text().splitlines()]
    n = cfg.eval.n_worlds or len(worlds)
    if n > len(worlds):
        raise ConfigError(f"eval.n_worlds={n} but the test split has {len(worlds)} worlds; allowed: 1..{len(worlds)} or null")
    decoder = make_decoder(cfg, finetune.artifact("model"))
    records = evaluate(
        decoder, worlds[:n], stats[:n], mode=spec.mode,
        direction=spec.direction or "fwd", variant=variant, max_steps=cfg.eval.max_steps,
        partial_path=step_dir / "episodes.partial.jsonl", prompt=spec.prompt,
    )
    episodes = step_dir / EPISODES_ARTIFACT
    episodes.write_text("".join(json.dumps(record) + "\n" for record in records))
    mlflow.log_artifact(str(episodes))
    mlflow.log_metrics(metrics(records))
    if cfg.eval.curve:
        _evaluate_curve(cfg, spec, variant, finetune, worlds, stats, step_dir)


# ---------------------------------------------------------------------------------------------------- job
def run_job(cfg: DictConfig) -> dict | None:
    """Run (or reuse) the job's three steps; return the eval metrics (None for a skipped grid cell)."""
    try:
        variant = validate(cfg)
    except UndefinedCell as error:
        if cfg.skip_undefined:
            log.info("skipped (undefined in the paper's grid): %s", error)
            return None
        raise
    direction, mode = str(cfg.direction.value), str(cfg.mode.value)
    spec = TextSpec.of(direction, variant, mode, seed=cfg.data.seed, prompt=cfg.model.prompt)
    hashes = step_hashes(cfg, spec)
    clear_inherited_run()
    from transformers.utils import logging as hf_logging

    hf_logging.disable_progress_bar()
    if cfg.threads:
        import torch

        torch.set_num_threads(cfg.threads)
    experiment_id = prepare_store(cfg)
    mlflow.set_tracking_uri(cfg.tracking.uri)
    mlflow.set_experiment(experiment_id=experiment_id)
    tags = {"direction": direction, "variant": variant, "mode": mode, "seed": str(cfg.seed),
            "paper_row": PAPER_ROWS[variant]}
    work_dir = Path(cfg.work_dir)
    train_max = dict(zip(TRAIN_MAX_TAGS, map(str, _train_max(cfg))))
    with mlflow.start_run(run_name=f"{direction}-{variant}-{mode}", tags={**tags, **train_max, KIND_TAG: JOB_KIND}) as job:
        mlflow.log_dict(OmegaConf.to_container(cfg, resolve=True, enum_to_str=True), "config.json")

        def step(name: str, body) -> StepRun:
            done = get_or_run(name, hashes[name], experiment_id=experiment_id, work_dir=work_dir, tags=tags, body=body)
            mlflow.set_tag(step_run_tag(name), done.run_id)
            log.info("%s: %s run %s", name, "reused" if done.reused else "ran", done.run_id)
            return done

        data = step("data-build", lambda d: data_build_body(cfg, spec, d))
        # The job's own row in the runs table names its data too (the step runs below it hold the same).
        _log_step_dataset(data, spec, TRAIN_CONVERSATIONS, "train", "training")
        _log_step_dataset(data, spec, TEST_CONVERSATIONS, "test", "evaluation")
        finetune = step("finetune", lambda d: finetune_body(cfg, spec, data, d))
        evaluation = step("eval", lambda d: eval_body(cfg, spec, variant, data, finetune, d))
        results = mlflow.get_run(evaluation.run_id).data.metrics
        mlflow.log_metrics({key: value for key, value in results.items() if key != "step_seconds"})
    reused = [s.step for s in (data, finetune, evaluation) if s.reused]
    print(
        f"[job] {direction} {variant} {mode}: success {results.get('success_rate', float('nan')):.3f} "
        f"(interp {results.get('success_rate_interp', float('nan')):.3f}, "
        f"extrap {results.get('success_rate_extrap', float('nan')):.3f}) over {int(results.get('n_episodes', 0))} "
        f"worlds | reused: {', '.join(reused) or 'nothing'} | job run {job.info.run_id}\n"
        f"      in `mlflow ui` (README): {UI_ADDRESS}/{ui_path(experiment_id, job.info.run_id)}",
        flush=True,
    )
    return results


@contextmanager
def errors_for_people():
    """A configuration or input error ends a single run with one line on stderr (``error: ...``) and exit
    status 2, without a traceback; ``HYDRA_FULL_ERROR=1`` shows the traceback. In a multirun the error is
    raised as usual, so the sweep records the failed job and goes on."""
    try:
        yield
    except (ConfigError, WorldError) as error:
        if os.environ.get("HYDRA_FULL_ERROR") == "1" or _multirun():
            raise
        print(f"error: {error}", file=sys.stderr, flush=True)
        raise SystemExit(2) from None


def _multirun() -> bool:
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    return HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN


def _interrupt(signum, frame) -> None:
    # A preempted job (SIGTERM from SLURM or a shell) unwinds like Ctrl-C, so its MLflow runs end FAILED/KILLED.
    raise KeyboardInterrupt(f"signal {signum}")


def main(cfg: DictConfig) -> float | None:
    """The Hydra task (`pipeline.run` decorates it); returns the success rate (what a sweeper would optimise)."""
    signal.signal(signal.SIGTERM, _interrupt)
    with errors_for_people():
        results = run_job(cfg)
    return None if results is None else results.get("success_rate")
