"""The finetune step: the model and tokenizer the settings name, trained through the one training entry
point (`pipeline.lm.training.entry`) in-process or, for distributed (FSDP) training, under ``accelerate
launch``; then the model logged to MLflow (artifacts and a logged model) with the run's metrics."""

from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path

import mlflow

from pipeline.core.bulk import bulk_building
from pipeline.lm.chat import read_conversations
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.result import CHECKPOINTS_DIR, TrainResult
from pipeline.workflow.data_build import TRAIN_CONVERSATIONS, TextSettings, log_step_dataset
from pipeline.workflow.steps import StepRun
from pipeline.workflow.tracking import CHECKPOINTS_ARTIFACT, log_settings

log = logging.getLogger(__name__)

# The Trainer writes a checkpoint's files in turn and its trainer_state.json last.
_CHECKPOINT_DONE = "trainer_state.json"


def run_finetune_step(model: ModelSettings, settings: TrainSettings, seed: int, frame: int, texts: TextSettings,
                      data: StepRun, step_dir: Path) -> None:
    """The finetune step's body (inside its MLflow run): train, then log metrics, the model and checkpoints."""
    # Prefixed: transformers' MLflowCallback logs the Trainer's own arguments under their plain names.
    log_settings(model.to_dict(), "model")
    log_settings(settings.to_dict(), "train")
    train_file = data.artifact(TRAIN_CONVERSATIONS)
    log_step_dataset(data, texts, TRAIN_CONVERSATIONS, "train", "training")
    result = run_training(model, settings, seed, frame, train_file, step_dir)
    mlflow.log_param("model.parameters", result.parameters)
    mlflow.log_metrics(result_metrics(result))
    if result.token_accuracy is not None:
        mlflow.log_metric("eval_token_accuracy", result.token_accuracy, step=result.global_step)
    mlflow.log_artifacts(result.model_dir, "model")
    log_model(model, result.model_dir)
    if settings.log_checkpoints:
        mlflow.log_artifacts(str(_checkpoint_models(step_dir, Path(result.model_dir))), CHECKPOINTS_ARTIFACT)


def run_training(model: ModelSettings, settings: TrainSettings, seed: int, frame: int, train_file: str,
                 step_dir: Path) -> TrainResult:
    """Train on the conversations at ``train_file`` into ``step_dir``, resuming from its last complete
    checkpoint if an earlier run was interrupted."""
    # torch and transformers only when there is training to do (not for a reused step, nor at config time).
    from pipeline.lm.models import make_tokenizer
    from pipeline.lm.training.entry import TrainRequest, launch, train

    discard_incomplete_checkpoints(step_dir)
    with bulk_building():  # the training conversations
        conversations = read_conversations(train_file)
    tokenizer = make_tokenizer(model, (turn["value"] for turns in conversations for turn in turns), frame)
    mlflow.log_param("model.vocab_size", len(tokenizer))
    tokenizer_dir = step_dir / "tokenizer"
    tokenizer.save_pretrained(str(tokenizer_dir))
    request = TrainRequest(model=model, train=settings, seed=seed, data=str(train_file),
                           tokenizer_dir=str(tokenizer_dir), output_dir=str(step_dir))
    if settings.accelerate_config:
        # Rank 0's MLflowCallback logs into this run: the processes find it through the environment.
        return launch(request, env={"MLFLOW_TRACKING_URI": mlflow.get_tracking_uri(),
                                    "MLFLOW_RUN_ID": mlflow.active_run().info.run_id})
    return train(request, conversations)


def discard_incomplete_checkpoints(step_dir: Path) -> list[Path]:
    """Delete checkpoints a killed run left half-written (no readable trainer_state.json, which the
    Trainer writes last), so resuming picks the last complete one instead of failing on a torn one."""
    folder = Path(step_dir) / CHECKPOINTS_DIR
    removed = []
    for checkpoint in sorted(folder.glob("checkpoint-*")) if folder.is_dir() else []:
        try:
            json.loads((checkpoint / _CHECKPOINT_DONE).read_text())
            continue
        except (OSError, ValueError):
            pass
        log.warning("discarding incomplete checkpoint %s (its run was interrupted while saving it)", checkpoint)
        shutil.rmtree(checkpoint, ignore_errors=True)
        removed.append(checkpoint)
    return removed


def result_metrics(result: TrainResult) -> dict[str, float]:
    """The finetune run's summary metrics (the Trainer logs the per-step curves itself)."""
    values = {
        "final_loss": result.final_loss, "mean_loss": result.mean_loss, "token_accuracy": result.token_accuracy,
        "tokens_trained": result.tokens_trained, "real_token_fraction": result.real_token_fraction,
        "tokens_per_second": result.tokens_per_second, "train_seconds": result.train_seconds,
        "global_step": result.global_step, "dropped_conversations": result.dropped,
        "truncated_conversations": result.truncated,
    }
    return {key: float(value) for key, value in values.items() if value is not None}


def log_model(model: ModelSettings, model_dir: str) -> None:
    """The finetuned model as an MLflow logged model: the transformers flavour (weights copied, loadable with
    ``mlflow.transformers.load_model``), or for large models a reference to the run's ``model/`` artifacts."""
    import transformers

    if model.log_model == "transformers":
        import mlflow.transformers as mlflow_transformers  # `as`: binds no local `mlflow` over the module's
        import torch

        from pipeline.lm.models import load_model, load_tokenizer

        # From the loaded model, not the folder: MLflow 3.17 cannot read a transformers 5 checkpoint folder
        # (its task table holds class names as strings there).
        loaded = load_model(model_dir, dtype=model.dtype, trust_remote_code=model.trust_remote_code)
        tokenizer = load_tokenizer(model_dir, trust_remote_code=model.trust_remote_code)
        quiet = logging.getLogger("mlflow.transformers")
        level = quiet.level
        quiet.setLevel(logging.ERROR)  # no model card or licence to look up for a model trained here
        try:
            mlflow_transformers.log_model(
                {"model": loaded, "tokenizer": tokenizer}, name="model", task="text-generation",
                pip_requirements=[f"torch=={torch.__version__.split('+')[0]}",
                                  f"transformers=={transformers.__version__}"],
            )
        finally:
            quiet.setLevel(level)
    else:
        run_id = mlflow.active_run().info.run_id
        mlflow.create_external_model(name="model", source_run_id=run_id, model_type="transformers",
                                     params={"weights": f"runs:/{run_id}/model"})



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


