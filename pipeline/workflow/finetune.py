"""The finetune step's body: the model and tokenizer the config names, trained in-process or, for
distributed (FSDP) training, under `accelerate launch` with a resolved spec and an explicit output dir."""

from __future__ import annotations

import json
import logging
import shutil
import subprocess
import sys
from dataclasses import asdict
from pathlib import Path

import mlflow
from omegaconf import DictConfig, OmegaConf

from pipeline.lm.chat import ChatFormat
from pipeline.lm.training.trainer import CHECKPOINTS_DIR, RESULT_FILE, TrainResult, TrainSettings, finetune
from pipeline.lm.models import build_scratch_model, load_model, load_tokenizer
from pipeline.lm.tokenizer import build_word_tokenizer

log = logging.getLogger(__name__)

# The Trainer writes a checkpoint's files in turn and its trainer_state.json last.
_CHECKPOINT_DONE = "trainer_state.json"

# TrainConfig keys that steer the step rather than the Trainer.
_STEP_KEYS = ("accelerate_config", "log_checkpoints")


def train_settings(cfg: DictConfig) -> TrainSettings:
    """TrainSettings from the job config (the job's seed seeds training)."""
    values = OmegaConf.to_container(cfg.train, resolve=True, enum_to_str=True)
    for key in _STEP_KEYS:
        values.pop(key)
    return TrainSettings.from_dict({**values, "seed": cfg.seed})


def chat_format(cfg: DictConfig) -> ChatFormat:
    return ChatFormat(**OmegaConf.to_container(cfg.model.chat_format, resolve=True))


def _scratch_kwargs(cfg: DictConfig) -> dict:
    model = cfg.model
    return dict(hidden_size=model.hidden_size, num_layers=model.num_layers, num_heads=model.num_heads,
                intermediate_size=model.intermediate_size, max_length=model.max_length,
                attn_implementation=model.attn_implementation, seed=cfg.seed)


def _tokenizer(cfg: DictConfig, conversations: list[list[dict]]):
    if cfg.model.kind.value == "scratch":
        texts = (turn["value"] for turns in conversations for turn in turns)
        return build_word_tokenizer(texts, frame=cfg.data.frame)
    return load_tokenizer(cfg.model.path, trust_remote_code=cfg.model.trust_remote_code)


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


def run_finetune(cfg: DictConfig, conversations: list[list[dict]], train_file: str, step_dir: Path) -> TrainResult:
    """Train the configured model on ``conversations`` (also at ``train_file``) into ``step_dir``, resuming
    from its last complete checkpoint if an earlier run was interrupted."""
    discard_incomplete_checkpoints(step_dir)
    settings = train_settings(cfg)
    fmt = chat_format(cfg)
    tokenizer = _tokenizer(cfg, conversations)
    mlflow.log_param("model.vocab_size", len(tokenizer))
    if cfg.train.accelerate_config:
        return _launch_distributed(cfg, settings, fmt, tokenizer, train_file, step_dir)
    if cfg.model.kind.value == "scratch":
        model = build_scratch_model(tokenizer, **_scratch_kwargs(cfg))
    else:
        model = load_model(cfg.model.path, dtype=cfg.model.dtype, trust_remote_code=cfg.model.trust_remote_code,
                           attn_implementation=cfg.model.attn_implementation)
    mlflow.log_param("model.parameters", model.num_parameters())
    return finetune(model, tokenizer, fmt, conversations, settings, step_dir)


def _launch_distributed(cfg, settings: TrainSettings, fmt: ChatFormat, tokenizer, train_file: str, step_dir: Path) -> TrainResult:
    # Each rank would resolve ${now:} and the like itself: hand it a fully resolved spec instead.
    tokenizer_dir = step_dir / "tokenizer"
    tokenizer.save_pretrained(str(tokenizer_dir))
    source = ({"scratch": _scratch_kwargs(cfg)} if cfg.model.kind.value == "scratch"
              else {"path": cfg.model.path, "dtype": cfg.model.dtype,
                    "attn_implementation": cfg.model.attn_implementation})
    spec = {
        "tokenizer_dir": str(tokenizer_dir), "data": train_file, "output_dir": str(step_dir),
        "settings": {**asdict(settings), "report_to": list(settings.report_to)},
        "model": source, "chat_format": asdict(fmt),
        "mlflow": {"tracking_uri": mlflow.get_tracking_uri(), "run_id": mlflow.active_run().info.run_id},
    }
    spec_path = step_dir / "finetune_spec.json"
    spec_path.write_text(json.dumps(spec, indent=2))
    command = [sys.executable, "-m", "accelerate.commands.launch", "--config_file", str(cfg.train.accelerate_config),
               "-m", "pipeline.lm.training.trainer", "--spec", str(spec_path)]
    subprocess.run(command, check=True)
    return TrainResult(**json.loads((step_dir / RESULT_FILE).read_text()))


def result_metrics(result: TrainResult) -> dict[str, float]:
    """The finetune run's summary metrics (the Trainer logs the per-step curves itself)."""
    values = {
        "final_loss": result.final_loss, "mean_loss": result.mean_loss, "token_accuracy": result.token_accuracy,
        "tokens_trained": result.tokens_trained, "real_token_fraction": result.real_token_fraction,
        "tokens_per_second": result.tokens_per_second, "train_seconds": result.train_seconds,
        "global_step": result.global_step, "dropped_conversations": result.dropped,
    }
    return {key: float(value) for key, value in values.items() if value is not None}
