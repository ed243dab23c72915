"""Supervised fine-tuning on Gridworld conversations with transformers' Trainer (SPEC 5's setup).

The paper's schedule: cosine decay, warmup ratio 0.03, weight decay 0, loss on gpt turns only. Metrics go
through transformers' MLflowCallback into the active MLflow run. Checkpoints live in
``output_dir/checkpoints/checkpoint-<step>``; calling `finetune` again with the same ``output_dir`` resumes
from the last one. The final model (safetensors), its tokenizer and chat format go to ``output_dir/model``.

Throughput: with ``packing`` (the default) batches are grouped by length and right-padded *without* an
attention mask. Causal attention never looks right, so the padding cannot reach a real token and each
sequence computes exactly what it would alone, while SDPA keeps its fast ``is_causal`` kernel; grouping keeps
the padding to a few percent. Flattening a batch into one row (``DataCollatorWithFlattening``) is exact in
transformers 5 only when no KV cache is created (``use_cache=False``, which Trainer sets), and on CPU its
block-diagonal mask costs attention over the whole row: about 3x slower here.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import random
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Sequence

import torch
from transformers import PreTrainedModel, PreTrainedTokenizerBase, Trainer, TrainerCallback, TrainingArguments
from transformers.trainer_callback import ProgressCallback
from transformers.trainer_utils import PREFIX_CHECKPOINT_DIR, get_last_checkpoint

from pipeline.workflow.data_build import read_conversations
from pipeline.lm.chat import IGNORE_INDEX, WORD_LEVEL_FORMAT, ChatFormat, encode_conversation
from pipeline.workflow.config import CompileMode
from pipeline.lm.models import build_scratch_model, load_model, load_tokenizer, save_chat_format

log = logging.getLogger(__name__)

REPORT_TARGETS = ("mlflow",)
SCHEDULERS = ("cosine", "linear", "constant", "constant_with_warmup", "cosine_with_restarts", "polynomial")
# torch.compile scopes (the config's CompileMode): none, regional, full. See TrainSettings.
COMPILE_MODES = tuple(mode.value for mode in CompileMode)
DYNAMO_ENV_PREFIX = "ACCELERATE_DYNAMO_"
CHECKPOINTS_DIR, MODEL_DIR, RESULT_FILE = "checkpoints", "model", "train_result.json"


@dataclass
class TrainSettings:
    """Everything that decides a fine-tuning run besides the model and the data.

    ``max_steps`` (optimizer steps) wins over ``num_epochs`` when set. ``per_device_batch_size`` counts
    sequences; the effective batch is it times ``gradient_accumulation_steps`` times the number of devices
    (the paper: 16). ``eval_fraction`` of the conversations is held out for a token-accuracy eval.
    ``pad_to_multiple_of`` rounds each batch's width up: a few distinct shapes instead of one per length,
    so the matmul kernels that oneDNN builds per shape (bf16 on a CPU) are built a few times, not hundreds.
    ``torch_compile`` is what torch.compile (inductor) compiles: ``"none"``; ``"regional"``, each repeated
    block (decoder layer) in place, one graph shared by the layers; or ``"full"``, the whole model, through
    Trainer. On the 2-core CPU default both compiled scopes make steps about 1.25x faster; ``regional`` compiles
    in about 55 s with an empty inductor cache and 5-10 s from a warm one, ``full`` in about 180 s and 60 s.
    On a CPU compiling needs a C++ compiler and the Python headers.
    """

    max_steps: int | None = None
    num_epochs: float = 1.0
    per_device_batch_size: int = 16
    gradient_accumulation_steps: int = 1
    learning_rate: float = 1e-3
    lr_scheduler_type: str = "cosine"
    warmup_ratio: float = 0.03
    weight_decay: float = 0.0
    max_grad_norm: float = 1.0
    max_length: int = 2048
    packing: bool = True
    pad_to_multiple_of: int = 8
    seed: int = 0
    logging_steps: int = 10
    save_steps: int = 500
    save_total_limit: int | None = 2
    bf16: bool = False
    torch_compile: str = "none"
    report_to: tuple[str, ...] = ("mlflow",)
    dataloader_num_workers: int = 0
    torch_threads: int | None = None
    eval_fraction: float = 0.0

    def __post_init__(self) -> None:
        self.report_to = (self.report_to,) if isinstance(self.report_to, str) else tuple(self.report_to)
        if self.max_steps is not None:
            _require(isinstance(self.max_steps, int) and self.max_steps > 0, "max_steps", self.max_steps,
                     "a positive integer, or None to train num_epochs")
        _require(self.num_epochs > 0, "num_epochs", self.num_epochs, "a positive number")
        for name in ("per_device_batch_size", "gradient_accumulation_steps", "max_length", "logging_steps",
                     "save_steps", "pad_to_multiple_of"):
            value = getattr(self, name)
            _require(isinstance(value, int) and value > 0, name, value, "a positive integer")
        _require(self.learning_rate > 0, "learning_rate", self.learning_rate, "a positive number")
        _require(self.lr_scheduler_type in SCHEDULERS, "lr_scheduler_type", self.lr_scheduler_type,
                 f"one of {', '.join(SCHEDULERS)}")
        _require(0 <= self.warmup_ratio < 1, "warmup_ratio", self.warmup_ratio, "a ratio in [0, 1)")
        _require(self.weight_decay >= 0, "weight_decay", self.weight_decay, "a number >= 0")
        _require(self.max_grad_norm > 0, "max_grad_norm", self.max_grad_norm, "a positive number")
        _require(self.save_total_limit is None or self.save_total_limit > 0, "save_total_limit",
                 self.save_total_limit, "a positive integer, or None to keep every checkpoint")
        _require(set(self.report_to) <= set(REPORT_TARGETS), "report_to", self.report_to,
                 f"a subset of {REPORT_TARGETS} (empty: report nowhere)")
        _require(self.dataloader_num_workers >= 0, "dataloader_num_workers", self.dataloader_num_workers,
                 "an integer >= 0")
        _require(self.torch_threads is None or self.torch_threads > 0, "torch_threads", self.torch_threads,
                 "a positive integer, or None to leave torch's setting")
        _require(0 <= self.eval_fraction < 1, "eval_fraction", self.eval_fraction, "a fraction in [0, 1)")
        _require(self.torch_compile in COMPILE_MODES, "torch_compile", self.torch_compile,
                 f"one of {', '.join(COMPILE_MODES)}")

    @classmethod
    def from_dict(cls, values: dict) -> "TrainSettings":
        """Settings from a plain mapping (a resolved config); unknown keys are an error, not ignored."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ValueError(f"unknown train settings {unknown}; allowed: {sorted(known)}")
        return cls(**values)


def _require(ok: bool, name: str, value: object, allowed: str) -> None:
    if not ok:
        raise ValueError(f"{name}={value!r} is not allowed; expected {allowed}")


class ConversationDataset(torch.utils.data.Dataset):
    """Tokenized conversations (``input_ids``, ``labels``); ``dropped`` counts those over ``max_length``."""

    def __init__(self, examples: list[dict[str, list[int]]], dropped: int = 0):
        self.examples = examples
        self.dropped = dropped

    def __len__(self) -> int:
        return len(self.examples)

    def __getitem__(self, index: int) -> dict[str, list[int]]:
        return self.examples[index]

    @property
    def lengths(self) -> list[int]:
        return [len(example["input_ids"]) for example in self.examples]


def tokenize_conversations(
    tokenizer: PreTrainedTokenizerBase, fmt: ChatFormat, conversations: Sequence[Sequence[dict]], max_length: int
) -> ConversationDataset:
    """Encode conversations with loss on gpt turns only. One longer than ``max_length`` is dropped and
    counted (truncating it would train on a cut-off answer)."""
    examples, dropped = [], 0
    for turns in conversations:
        input_ids, labels = encode_conversation(tokenizer, fmt, turns)
        if len(input_ids) > max_length:
            dropped += 1
            continue
        examples.append({"input_ids": input_ids, "labels": labels})
    if dropped:
        log.warning("dropped %d of %d conversations longer than max_length=%d tokens",
                    dropped, len(conversations), max_length)
    return ConversationDataset(examples, dropped)


@dataclass
class RightPadCollator:
    """Pads to the longest sequence on the right. With ``attention_mask=False`` (packing) no mask is sent:
    causal attention keeps every real token blind to the padding after it, and SDPA uses ``is_causal``."""

    pad_token_id: int
    attention_mask: bool = False
    pad_to_multiple_of: int = 1

    def __call__(self, features: list[dict]) -> dict[str, torch.Tensor]:
        width = max(len(f["input_ids"]) for f in features)
        width = -(-width // self.pad_to_multiple_of) * self.pad_to_multiple_of
        input_ids = torch.full((len(features), width), self.pad_token_id, dtype=torch.long)
        labels = torch.full((len(features), width), IGNORE_INDEX, dtype=torch.long)
        mask = torch.zeros((len(features), width), dtype=torch.long)
        for row, f in enumerate(features):
            n = len(f["input_ids"])
            input_ids[row, :n] = torch.tensor(f["input_ids"])
            labels[row, :n] = torch.tensor(f["labels"])
            mask[row, :n] = 1
        batch = {"input_ids": input_ids, "labels": labels}
        if self.attention_mask:
            batch["attention_mask"] = mask
        return batch


class LengthGroupedBatches(torch.utils.data.Sampler[int]):
    """Indices whose consecutive ``batch_size`` runs are batches of similar length, in random batch order.

    Each epoch: a random permutation, cut into megabatches of ``megabatch_mult`` batches, each sorted by length
    and cut into batches; then the batches are shuffled. transformers' LengthGroupedSampler shrinks megabatches
    to a quarter of a small data set (8% padding on a few hundred conversations) and runs each megabatch from
    the longest batch to the shortest, a length curriculum we do not want. Randomness comes from torch's global
    generator, which Trainer seeds and restores on resume.
    """

    def __init__(self, lengths: Sequence[int], batch_size: int, megabatch_mult: int = 50):
        self.lengths, self.batch_size, self.megabatch_mult = list(lengths), batch_size, megabatch_mult

    def __len__(self) -> int:
        return len(self.lengths)

    def __iter__(self):
        order = torch.randperm(len(self.lengths)).tolist()
        size = self.batch_size * self.megabatch_mult
        batches = []
        for start in range(0, len(order), size):
            megabatch = sorted(order[start:start + size], key=self.lengths.__getitem__)
            batches += [megabatch[i:i + self.batch_size] for i in range(0, len(megabatch), self.batch_size)]
        return iter([i for b in torch.randperm(len(batches)).tolist() for i in batches[b]])


class BarProgress(ProgressCallback):
    """Trainer's progress bar with the last loss and tokens/s in it; the raw log dicts go to the logger
    (DEBUG) instead of being printed through the bar, where they break it into many lines."""

    def on_log(self, args, state, control, logs=None, **kwargs):
        if not state.is_world_process_zero or self.training_bar is None or not logs:
            return
        log.debug("trainer log at step %d: %s", state.global_step, logs)
        shown = {}
        if "loss" in logs:
            shown["loss"] = f"{float(logs['loss']):.4f}"
        if "train_tokens_per_second" in logs:
            shown["tok/s"] = f"{float(logs['train_tokens_per_second']):,.0f}"
        elif "loss" in logs and state.num_input_tokens_seen and self._started is not None:
            shown["tok/s"] = f"{state.num_input_tokens_seen / max(time.perf_counter() - self._started, 1e-9):,.0f}"
        if shown:
            self.training_bar.set_postfix(shown, refresh=False)

    def on_train_begin(self, args, state, control, **kwargs):
        self._started = time.perf_counter()
        return super().on_train_begin(args, state, control, **kwargs)

    _started: float | None = None


class _PackingTrainer(Trainer):
    """Trainer drawing its training batches from `LengthGroupedBatches`."""

    def _get_train_sampler(self, train_dataset=None):
        dataset = train_dataset if train_dataset is not None else self.train_dataset
        return LengthGroupedBatches(dataset.lengths, self.args.per_device_train_batch_size)


@dataclass
class TrainResult:
    """What a fine-tuning run produced and how fast."""

    final_loss: float | None          # the last logged training loss
    mean_loss: float                  # mean training loss of this session (transformers' train_loss)
    token_accuracy: float | None      # argmax accuracy on held-out gpt tokens (None: no eval split)
    tokens_trained: int               # real (non-padding) tokens over the whole run, resumed part included
    real_token_fraction: float        # real tokens / tokens computed, over the whole run
    tokens_per_second: float          # real tokens per second of this session
    train_seconds: float              # wall time of this session's training loop
    global_step: int
    model_dir: str
    checkpoint_steps: list[int] = field(default_factory=list)
    dropped: int = 0                  # conversations over max_length, not trained on
    resumed_from: str | None = None


def split_eval(conversations: Sequence, fraction: float, seed: int) -> tuple[list, list]:
    """A seeded (train, eval) split holding out ``fraction`` of the conversations."""
    order = list(range(len(conversations)))
    random.Random(seed).shuffle(order)
    n_eval = math.floor(len(order) * fraction)
    held = set(order[:n_eval])
    train = [c for i, c in enumerate(conversations) if i not in held]
    return train, [conversations[i] for i in sorted(held)]


@torch.no_grad()
def token_accuracy(model: PreTrainedModel, dataset: ConversationDataset, pad_token_id: int,
                   batch_size: int = 16, *, sharded: bool = False) -> float | None:
    """Argmax next-token accuracy over every labelled (gpt) position; None if there is none.

    ``sharded``: the model is FSDP-wrapped, so only its root forward gathers the root's parameters (the
    embedding, final norm and head); that forward computes full-vocabulary logits.
    """
    if len(dataset) == 0:
        return None
    model.eval()
    collate = RightPadCollator(pad_token_id)
    order = sorted(range(len(dataset)), key=lambda i: len(dataset[i]["input_ids"]))
    correct = total = 0
    head, device = model.get_output_embeddings(), next(model.parameters()).device
    for start in range(0, len(order), batch_size):
        batch = collate([dataset[i] for i in order[start:start + batch_size]])
        input_ids = batch["input_ids"].to(device)
        targets = batch["labels"][:, 1:].to(device)
        keep = targets != IGNORE_INDEX
        if sharded:
            predictions = model(input_ids=input_ids).logits[:, :-1][keep].argmax(-1)
        else:
            # Project only labelled positions: a full-vocabulary logits tensor would dwarf the batch.
            hidden = model.base_model(input_ids=input_ids).last_hidden_state[:, :-1]
            predictions = head(hidden[keep]).argmax(-1)
        correct += (predictions == targets[keep]).sum().item()
        total += keep.sum().item()
    return correct / total if total else None


def cpu_has_bf16(cpuinfo: str | None = None) -> bool:
    """Whether this CPU multiplies bf16 matrices in hardware (AVX512-BF16 or AMX on x86; any Arm/Apple CPU
    torch runs bf16 on is trusted). Without it oneDNN emulates bf16, measured at 0.3 GFLOP/s on an AVX2 CPU."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text()
        except OSError:  # not Linux: nothing to read, trust torch
            return True
    flags = next((line.split(":", 1)[1].split() for line in cpuinfo.splitlines() if line.startswith("flags")), None)
    if flags is None:  # no x86 flags line (e.g. Arm's "Features"): trust torch
        return True
    return bool({"avx512_bf16", "amx_bf16"} & set(flags))


def use_bf16(requested: bool) -> bool:
    """bf16 as asked, except on a CPU without bf16 hardware, which trains in fp32 instead (with a warning)."""
    if requested and not torch.cuda.is_available() and not cpu_has_bf16():
        log.warning("train.bf16=true but this CPU has no bf16 matmul hardware (no avx512_bf16 or amx_bf16 flag): "
                    "training in fp32 instead")
        return False
    return requested


def _training_arguments(settings: TrainSettings, checkpoints: Path) -> TrainingArguments:
    bf16 = use_bf16(settings.bf16)
    return TrainingArguments(
        output_dir=str(checkpoints),
        max_steps=settings.max_steps if settings.max_steps is not None else -1,
        num_train_epochs=settings.num_epochs,
        per_device_train_batch_size=settings.per_device_batch_size,
        gradient_accumulation_steps=settings.gradient_accumulation_steps,
        learning_rate=settings.learning_rate,
        lr_scheduler_type=settings.lr_scheduler_type,
        warmup_steps=settings.warmup_ratio,  # a float in [0, 1) is a ratio of the total steps (transformers 5)
        weight_decay=settings.weight_decay,
        max_grad_norm=settings.max_grad_norm,
        seed=settings.seed,
        logging_steps=settings.logging_steps,
        save_strategy="steps",
        save_steps=settings.save_steps,
        save_total_limit=settings.save_total_limit,
        bf16=bf16,
        # bf16 without a GPU is CPU autocast (AMX/AVX512-BF16 matmuls); transformers asks for use_cpu then.
        use_cpu=bf16 and not torch.cuda.is_available(),
        torch_compile=settings.torch_compile == "full",  # regional: _compiled_blocks, in place
        report_to=list(settings.report_to) or "none",
        dataloader_num_workers=settings.dataloader_num_workers,
        include_num_input_tokens_seen="non_padding",
        remove_unused_columns=False,
        dataloader_pin_memory=False,  # nothing to pin for on a CPU; on a GPU the gain is negligible here
    )


@contextmanager
def _dynamo_environment():
    """The environment in which a Trainer is built: no ``ACCELERATE_DYNAMO_*`` variables.

    accelerate's TorchDynamoPlugin, which Trainer builds, takes from these variables whatever Trainer does not
    pass: the backend when ``torch_compile`` is off, and the mode, dynamic shapes and regional compilation
    always. ``accelerate launch`` sets them from its config, and so did TrainingArguments with accelerate
    before 1.2. Left in place, they would compile a job whose ``train.torch_compile`` is ``none`` (or change
    how a ``full`` job compiles): ``train.torch_compile`` alone decides, so a ``dynamo_config`` in an
    accelerate config is not used. Outside this block the variables are as they were.
    """
    saved = {key: value for key, value in os.environ.items() if key.startswith(DYNAMO_ENV_PREFIX)}
    for key in saved:
        del os.environ[key]
    try:
        yield
    finally:
        for key in [key for key in os.environ if key.startswith(DYNAMO_ENV_PREFIX)]:
            del os.environ[key]
        os.environ.update(saved)


@contextmanager
def _compiled_blocks(model: torch.nn.Module, torch_compile: str):
    """With ``regional``, compile every block of the model's repeated blocks (a decoder's layers: the
    ModuleLists whose members share a class) in place while the block runs, then put them back to eager.

    In place, so parameter names, checkpoints and the saved model are those of the plain model. Blocks of one
    class share their compiled code, so a 4-layer model compiles one layer (twice: the first batch width
    static, then one graph for every width). accelerate's regional compilation also compiles the small
    modules around the blocks, each apart; through Trainer that ran slower than eager here. Dynamo's caches
    are reset afterwards, so the next job in the same process starts under no guards or recompile counts of
    this one (inductor's on-disk cache keeps the compiled kernels).
    """
    if torch_compile != "regional":
        yield
        return
    blocks = [block for module in model.modules() if isinstance(module, torch.nn.ModuleList) and len(module) > 1
              and len({type(block) for block in module}) == 1 for block in module]
    for block in blocks:
        block.compile()
    try:
        yield
    finally:
        for block in blocks:
            block._compiled_call_impl = None  # what nn.Module.compile set: calls go to the eager forward again
        torch._dynamo.reset()


def checkpoint_steps(output_dir: str | Path) -> list[int]:
    """Steps of the checkpoints present under ``output_dir/checkpoints``, ascending."""
    folder = Path(output_dir) / CHECKPOINTS_DIR
    prefix = f"{PREFIX_CHECKPOINT_DIR}-"
    if not folder.is_dir():
        return []
    return sorted(int(p.name[len(prefix):]) for p in folder.glob(f"{prefix}*")
                  if p.is_dir() and p.name[len(prefix):].isdigit())


def finetune(
    model: PreTrainedModel,
    tokenizer: PreTrainedTokenizerBase,
    fmt: ChatFormat,
    conversations: Sequence[Sequence[dict]],
    settings: TrainSettings,
    output_dir: str | Path,
    *,
    callbacks: Sequence[TrainerCallback] = (),
) -> TrainResult:
    """Fine-tune ``model`` on ``conversations`` (loss on gpt turns), resuming from the last checkpoint in
    ``output_dir`` if there is one, and save the final model to ``output_dir/model``.

    With ``"mlflow"`` in ``settings.report_to``, transformers' MLflowCallback logs the Trainer's arguments
    as params and ``loss``, ``learning_rate``, ``grad_norm`` ... by step into the active run (it starts and
    ends a run of its own if none is active); the held-out ``eval_token_accuracy`` is logged to the active
    run only.
    """
    threads = torch.get_num_threads()
    if settings.torch_threads is not None:
        torch.set_num_threads(settings.torch_threads)
    try:
        return _finetune(model, tokenizer, fmt, conversations, settings, Path(output_dir), callbacks)
    finally:
        torch.set_num_threads(threads)  # jobs sharing a process (Hydra's basic launcher) keep their own


def _finetune(model, tokenizer, fmt, conversations, settings, output_dir, callbacks) -> TrainResult:
    # Checkpoints are many and large: the final model is logged once by the caller instead.
    os.environ["HF_MLFLOW_LOG_ARTIFACTS"] = "FALSE"
    checkpoints = output_dir / CHECKPOINTS_DIR
    checkpoints.mkdir(parents=True, exist_ok=True)

    train_part, eval_part = split_eval(conversations, settings.eval_fraction, settings.seed)
    train_data = tokenize_conversations(tokenizer, fmt, train_part, settings.max_length)
    eval_data = tokenize_conversations(tokenizer, fmt, eval_part, settings.max_length)
    if len(train_data) == 0:
        raise ValueError(f"no training conversation fits max_length={settings.max_length} "
                         f"({train_data.dropped} dropped)")

    with _dynamo_environment():
        trainer = (_PackingTrainer if settings.packing else Trainer)(
            model=model,
            args=_training_arguments(settings, checkpoints),
            train_dataset=train_data,
            data_collator=RightPadCollator(tokenizer.pad_token_id, attention_mask=not settings.packing,
                                           pad_to_multiple_of=settings.pad_to_multiple_of),
            processing_class=tokenizer,
            callbacks=list(callbacks),
        )
    if any(isinstance(c, ProgressCallback) for c in trainer.callback_handler.callbacks):
        trainer.remove_callback(ProgressCallback)
        trainer.add_callback(BarProgress)
    resume = get_last_checkpoint(str(checkpoints))
    if resume:
        log.info("resuming from %s", resume)
    started = time.perf_counter()
    with _compiled_blocks(model, settings.torch_compile):
        output = trainer.train(resume_from_checkpoint=resume)
    train_seconds = time.perf_counter() - started

    model_dir = output_dir / MODEL_DIR
    trainer.model.config.use_cache = True  # Trainer turns the cache off for training; decoding wants it
    if trainer.is_fsdp_enabled:
        # Trainer.save_model writes nothing under a SHARDED_STATE_DICT plugin (the checkpoints' setting):
        # gather the full weights for the final model, which eval loads as plain safetensors.
        trainer.accelerator.state.fsdp_plugin.set_state_dict_type("FULL_STATE_DICT")
    trainer.save_model(str(model_dir))
    if trainer.is_world_process_zero():
        save_chat_format(fmt, model_dir)
    state = trainer.state
    accuracy = token_accuracy(trainer.model, eval_data, tokenizer.pad_token_id, settings.per_device_batch_size,
                              sharded=trainer.is_fsdp_enabled)
    if accuracy is not None and "mlflow" in settings.report_to and trainer.is_world_process_zero():
        import mlflow

        if mlflow.active_run() is not None:
            mlflow.log_metric("eval_token_accuracy", accuracy, step=state.global_step)

    losses = [entry["loss"] for entry in state.log_history if "loss" in entry]
    session_tokens = state.num_input_tokens_seen - trainer._initial_num_input_tokens_seen
    return TrainResult(
        final_loss=losses[-1] if losses else None,
        mean_loss=output.training_loss,
        token_accuracy=accuracy,
        tokens_trained=int(state.num_input_tokens_seen),
        real_token_fraction=_real_token_fraction(trainer),
        tokens_per_second=session_tokens / train_seconds if train_seconds > 0 else 0.0,
        train_seconds=train_seconds,
        global_step=state.global_step,
        model_dir=str(model_dir),
        checkpoint_steps=checkpoint_steps(output_dir),
        dropped=train_data.dropped + eval_data.dropped,
        resumed_from=resume,
    )


def _real_token_fraction(trainer: Trainer) -> float:
    # Trainer counts 6 * (non-embedding parameters) FLOPs for every token it computes, padding included,
    # so total_flos gives the tokens computed over the whole run (restored on resume, summed over ranks).
    per_token = 6 * trainer.model.num_parameters(exclude_embeddings=True)
    computed = trainer.state.total_flos / per_token if per_token else 0
    return trainer.state.num_input_tokens_seen / computed if computed else 0.0


def run_spec(spec: dict) -> TrainResult:
    """Fine-tune from a resolved spec: ``tokenizer_dir``, ``data`` (JSONL), ``output_dir``, ``settings``,
    ``model`` (``{"path": dir}`` or ``{"scratch": {build_scratch_model kwargs}}``), optional ``chat_format``
    and ``mlflow`` (``{"tracking_uri": ..., "run_id": ...}``: the run rank 0 logs into)."""
    settings = TrainSettings.from_dict(spec.get("settings", {}))
    tokenizer = load_tokenizer(spec["tokenizer_dir"])
    fmt = ChatFormat(**spec["chat_format"]) if "chat_format" in spec else WORD_LEVEL_FORMAT
    source = spec["model"]
    if "path" in source:
        model = load_model(source["path"], dtype=source.get("dtype", "float32"),
                           attn_implementation=source.get("attn_implementation"))
    else:
        model = build_scratch_model(tokenizer, **source.get("scratch", {}))
    conversations = read_conversations(spec["data"])
    tracking = spec.get("mlflow")
    if tracking and "mlflow" in settings.report_to and int(os.environ.get("RANK", "0")) == 0:
        import mlflow

        mlflow.set_tracking_uri(tracking["tracking_uri"])
        with mlflow.start_run(run_id=tracking["run_id"]):
            return finetune(model, tokenizer, fmt, conversations, settings, spec["output_dir"])
    return finetune(model, tokenizer, fmt, conversations, settings, spec["output_dir"])


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m pipeline.lm.training.trainer --spec spec.json`` (or under ``accelerate launch -m``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spec", required=True, help="resolved JSON spec (see run_spec)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    spec = json.loads(Path(args.spec).read_text())
    result = run_spec(spec)
    if int(os.environ.get("RANK", "0")) == 0:
        target = Path(spec["output_dir"]) / RESULT_FILE
        target.write_text(json.dumps(asdict(result), indent=2) + "\n")
        print(json.dumps(asdict(result)))


if __name__ == "__main__":
    main()
