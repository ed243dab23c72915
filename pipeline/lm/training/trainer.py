"""Supervised fine-tuning on Gridworld conversations with transformers' Trainer (the paper's setup).

Loss on gpt turns only. Metrics go through transformers' MLflowCallback into the active MLflow run, if any.
Checkpoints live in ``output_dir/checkpoints/checkpoint-<step>``; calling `finetune` again with the same
``output_dir`` resumes from the last one. The final model (safetensors), its tokenizer and chat format go to
``output_dir/model``. The one entry point that builds the model and calls this is
`pipeline.lm.training.entry.train`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import os
import time
from pathlib import Path
from typing import Sequence

import torch
import torch.nn.functional as F
from accelerate.utils import DistributedType
from transformers import PreTrainedModel, PreTrainedTokenizerBase, Trainer, TrainerCallback, TrainingArguments
from transformers.trainer_callback import ProgressCallback
from transformers.trainer_utils import PREFIX_CHECKPOINT_DIR, get_last_checkpoint

from pipeline.core.bulk import bulk_building, walked_once
from pipeline.lm.chat import IGNORE_INDEX, ChatFormat
from pipeline.lm.models import ComposedRows, save_chat_format
from pipeline.lm.training.batches import (
    ConversationDataset, LengthGroupedBatches, RightPadCollator, split_eval, stretched_batch_positions,
    tokenize_conversations,
)
from pipeline.lm.training.compile import compile_settings, compiled_blocks, dynamo_environment, use_bf16
from pipeline.lm.training.last_layer import hidden_from, not_cut, start_of_labels, trims
from pipeline.lm.training.optim import MuonAdamW, build_optimizer
from pipeline.lm.training.parts import PartThreads, split_rows
from pipeline.lm.training.result import CHECKPOINTS_DIR, MODEL_DIR, TrainResult
from pipeline.lm.training.settings import CompileMode, TrainSettings

log = logging.getLogger(__name__)



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


class _Trainer(Trainer):
    """Trainer, quiet about the one "missing key" that is not missing: a checkpoint of a model whose output
    head is tied to its input embedding holds the weight once, and resuming it warned ``There were missing
    keys in the checkpoint model loaded: ['lm_head.weight']`` (harmless: the head is re-tied).

    With ``position_stretch`` > 1 each training batch gets stretched position ids (`stretched_batch_positions`)
    drawn from (seed, step, micro-batch within the step): a resumed run draws what the uninterrupted one drew.

    With ``part_threads`` each micro-batch is cut into as many parts of consecutive rows (each padded as the
    collator pads), computed side by side (`pipeline.lm.training.parts`); the positions are drawn for the whole
    micro-batch first, so they are those of the uncut run. `finetune` gives the same threads Muon's step, and while
    they take it the calling thread takes the next step's batch (`fetch_ahead`); they also take the gradients' norm
    and clipping (`grad_norm_side_by_side`), work that otherwise kept both part threads waiting: 0.973x the step in
    one run switching the three on and off (README, Speed).

    With ``labelled_logits`` a training batch's loss is `labelled_loss` (the head at the labelled positions only),
    except where the whole model is compiled (``torch_compile=full``: its compiled forward computes the loss)."""

    position_stretch: float = 1.0
    part_threads: PartThreads | None = None
    labelled_logits: bool = False
    labelled_last_layer: bool = False
    _warned_head: bool = False
    _draw: tuple[int, int] = (-1, 0)   # (global step, micro-batches drawn in it)
    _trained: tuple | None = None     # (model, its parameters): `_clip_grad_norm`
    _fetching: tuple | None = None    # (epoch iterator, batches, device) of the last `get_batch_samples`
    _ahead: tuple | None = None       # (epoch iterator, what `get_batch_samples` returns): `fetch_ahead`'s
    _counted: tuple | None = None     # (model, its non-embedding parameters): `floating_point_ops`

    def _with_positions(self, model, inputs):
        if self.position_stretch > 1 and model.training and "position_ids" not in inputs:
            step, drawn = self._draw
            drawn = drawn + 1 if step == self.state.global_step else 0
            self._draw = (self.state.global_step, drawn)
            inputs = self._positioned(inputs, self.state.global_step, drawn)
        return inputs

    def _positioned(self, inputs, step: int, drawn: int):
        """``inputs`` with the stretched positions of the ``drawn``-th micro-batch of optimizer step ``step``."""
        key = (self.args.seed * 1_000_003 + step) * 1_009 + drawn
        return {**inputs, "position_ids": stretched_batch_positions(inputs["attention_mask"], self.position_stretch,
                                                                    key)}

    def get_batch_samples(self, epoch_iterator, num_batches, device):
        """Trainer's batches for the next optimizer step, or those `fetch_ahead` took from the same iterator."""
        ahead, self._ahead = self._ahead, None
        self._fetching = (epoch_iterator, num_batches, device)
        if ahead is not None and ahead[0] is epoch_iterator:
            return ahead[1]
        return super().get_batch_samples(epoch_iterator, num_batches, device)

    def fetch_ahead(self) -> None:
        """Take the next optimizer step's batch now (one micro-batch a step), its stretched positions drawn as that
        step will draw them: `finetune` calls this on the caller's thread while the part threads take Muon's step
        (`MuonAdamW.meanwhile`), so the collation and the draw leave the time between two steps, when both part
        threads wait. The same batches in the same order; nothing where this step is the last."""
        fetching, self._fetching = self._fetching, None
        if (fetching is None or self.args.gradient_accumulation_steps != 1
                or self.state.global_step + 1 >= self.state.max_steps):
            return
        iterator, _, device = fetching
        batches, count = super().get_batch_samples(iterator, 1, device)
        if self.position_stretch > 1:
            batches = [self._positioned(batch, self.state.global_step + 1, 0) for batch in batches]
        self._ahead = (iterator, (batches, count))

    def compute_loss(self, model, inputs, return_outputs=False, num_items_in_batch=None):
        inputs = self._with_positions(model, inputs)
        if (self.labelled_logits and model.training and not return_outputs and "labels" in inputs
                and self.accelerator.num_processes == 1 and self.args.n_gpu <= 1 and not self.args.torch_compile
                and self.label_smoother is None and self.compute_loss_func is None):
            net = self.accelerator.unwrap_model(model)
            if type(net).__name__ in PLAIN_HEAD_MODELS:
                with self.accelerator.autocast():  # what the prepared model's own forward enters
                    return labelled_loss(net, inputs, num_items_in_batch, self.labelled_last_layer)
            if not self._warned_head:
                self._warned_head = True
                log.warning("train.labelled_logits: %s is not one of %s (models whose logits are their head's "
                            "output): its own forward computes the loss instead", type(net).__name__,
                            ", ".join(PLAIN_HEAD_MODELS))
        return super().compute_loss(model, inputs, return_outputs=return_outputs, num_items_in_batch=num_items_in_batch)

    def training_step(self, model, inputs, num_items_in_batch=None):
        if self.part_threads is None:
            return super().training_step(model, inputs, num_items_in_batch)
        if num_items_in_batch is None:  # each part's loss must be a share of the whole batch's
            raise ValueError("batch_threads > 1 needs a model that takes num_items_in_batch (a causal LM does)")
        parts = split_rows(self._with_positions(model, inputs), self.part_threads.parts,
                           self.data_collator.pad_to_multiple_of)
        step = super().training_step
        calls = [functools.partial(step, model, part, num_items_in_batch) for part in parts]
        losses = self.part_threads.run(calls)
        return torch.stack(losses).sum()

    def floating_point_ops(self, inputs) -> int:
        """Trainer's count (6 x the batch's tokens x the non-embedding parameters), the parameters counted once, not
        at every step (a walk over the model's modules)."""
        main = getattr(self.model, "main_input_name", "input_ids")
        if main not in inputs or not hasattr(self.model, "num_parameters"):
            return super().floating_point_ops(inputs)
        if self._counted is None or self._counted[0] is not self.model:
            self._counted = (self.model, self.model.num_parameters(exclude_embeddings=True))
        return 6 * inputs[main].numel() * self._counted[1]

    def _clip_grad_norm(self, model):
        """What Trainer's clipping does (accelerate's total norm of the gradients, and the gradients scaled to
        ``max_grad_norm`` where it is larger), without multiplying every gradient by a coefficient of exactly 1 where
        it is not (most steps): on one process on a CPU without a gradient scaler; elsewhere Trainer's own."""
        if (self.accelerator.distributed_type != DistributedType.NO or self.accelerator.scaler is not None
                or self.args.device.type != "cpu" or self._has_mixed_mesh_grads(model)):
            return super()._clip_grad_norm(model)
        if self._trained is None or self._trained[0] is not model:  # the parameters listed once, not every step
            self._trained = (model, list(model.parameters()))
        parameters = [p for p in self._trained[1] if p.grad is not None]
        threads = self.part_threads
        if threads is None:
            total = self.accelerator.clip_grad_norm_(parameters, float("inf"))  # the norm alone, as accelerate takes it
        else:  # the same norm, the tensors shared out among the part threads
            total = grad_norm_side_by_side([p.grad for p in parameters], threads)
        if not total + 1e-6 <= self.args.max_grad_norm:  # torch's coefficient max_norm / (total + 1e-6): below 1 or nan
            if threads is None:
                torch.nn.utils.clip_grads_with_norm_(parameters, self.args.max_grad_norm, total)
            else:  # what clip_grads_with_norm_ multiplies the gradients by, on the part threads
                coefficient = torch.clamp(self.args.max_grad_norm / (total + 1e-6), max=1.0)
                threads.map([functools.partial(torch._foreach_mul_, share, coefficient)
                             for share in _shares([p.grad for p in parameters], threads.parts)])
        return total

    def _track_num_input_tokens(self, inputs):
        """Trainer's count of the real (non-padding) tokens seen, without its gather and tensor round trip where
        there is one process: the same sum."""
        if (self.args.include_num_input_tokens_seen == "non_padding" and self.accelerator.num_processes == 1
                and "attention_mask" in inputs and getattr(self.model, "main_input_name", "input_ids") in inputs):
            self.state.num_input_tokens_seen += int(inputs["attention_mask"].sum())
            return
        super()._track_num_input_tokens(inputs)

    def _issue_warnings_after_load(self, load_result) -> None:
        tied = getattr(self.model.config, "tie_word_embeddings", False)
        if tied and set(load_result.missing_keys) == {"lm_head.weight"} and not load_result.unexpected_keys:
            self.model.tie_weights()
            log.info("resumed checkpoint: lm_head.weight is tied to the input embedding (stored once)")
            return
        super()._issue_warnings_after_load(load_result)


def grad_norm_side_by_side(grads: list[torch.Tensor], threads: PartThreads) -> torch.Tensor:
    """What accelerate's ``clip_grad_norm_`` returns on one process for these gradients (torch's total norm: each
    tensor's norm, then the norm of those; then the norm of that one-element list), each tensor's norm taken on the
    part threads, the tensors shared out among them in order: the same numbers, on both cores (``_foreach_norm``
    takes each tensor's norm alone)."""
    norms = [n for share in threads.map([functools.partial(torch._foreach_norm, share, 2.0)
                                         for share in _shares(grads, threads.parts)]) for n in share]
    return torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(torch.stack(norms), 2.0)]), 2)


def _shares(tensors: list[torch.Tensor], parts: int) -> list[list[torch.Tensor]]:
    """``tensors`` cut into at most ``parts`` runs of about equal numbers of elements, in order."""
    total = sum(t.numel() for t in tensors)
    shares: list[list[torch.Tensor]] = [[] for _ in range(parts)]
    seen = 0
    for t in tensors:
        shares[min(parts - 1, seen * parts // max(total, 1))].append(t)
        seen += t.numel()
    return [share for share in shares if share]


# Causal LMs whose logits are their output head's plain output and whose loss is transformers' causal-LM loss
# (no logit soft-capping or scaling after the head), for which `labelled_loss` computes what their forward does.
PLAIN_HEAD_MODELS = ("LlamaForCausalLM", "SmolLM3ForCausalLM")


def labelled_loss(model: PreTrainedModel, inputs: dict[str, torch.Tensor],
                  num_items_in_batch: torch.Tensor | int | None = None, last_layer: bool = False) -> torch.Tensor:
    """A causal LM's next-token loss on ``inputs`` (the model's inputs and ``labels``), as its own forward computes
    it (logits upcast to fp32, cross-entropy summed over the labelled positions and divided by
    ``num_items_in_batch``, or averaged over them), with the output head applied at the labelled positions alone:
    the CPU default trains on about two thirds of its positions, and at its vocabulary the head and the loss were
    about an eighth of a step (README, Speed). With ``last_layer``, the last decoder layer too is computed only
    from the first labelled position on, where `pipeline.lm.training.last_layer.trims` the model. The same loss
    and gradients, rounded otherwise."""
    logits, targets = head_at_labels(model, inputs, last_layer)
    loss = F.cross_entropy(logits.float(), targets, reduction="sum")
    return loss / (num_items_in_batch if num_items_in_batch is not None else len(targets))


def head_at_labels(model: PreTrainedModel, inputs: dict[str, torch.Tensor], last_layer: bool = False
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """The logits at the positions whose next token is labelled (``labels`` beside the model's inputs), computed
    from the base model's hidden states there alone, and those labels: ``(n, vocabulary)`` and ``(n,)``. With
    ``last_layer`` (and a model `last_layer.trims`), the last layer computed from the first of them on
    (`last_layer.hidden_from`)."""
    targets = inputs["labels"][:, 1:]
    keep = targets != IGNORE_INDEX
    model_inputs = {k: v for k, v in inputs.items() if k != "labels"}
    base = model.base_model
    if last_layer and trims(base) and set(model_inputs) <= {"input_ids", "attention_mask", "position_ids"}:
        start = start_of_labels(keep)
        hidden = hidden_from(base, model_inputs, start)
        return model.get_output_embeddings()(hidden[:, :-1][keep[:, start:]]), targets[keep]
    hidden = base(**model_inputs).last_hidden_state
    return model.get_output_embeddings()(hidden[:, :-1][keep]), targets[keep]


class _PackingTrainer(_Trainer):
    """Trainer drawing its training batches from `LengthGroupedBatches`."""

    def _get_train_sampler(self, train_dataset=None):
        dataset = train_dataset if train_dataset is not None else self.train_dataset
        return LengthGroupedBatches(dataset.lengths, self.args.per_device_train_batch_size)


@torch.no_grad()
def token_accuracy(model: PreTrainedModel, dataset: ConversationDataset, pad_token_id: int,
                   batch_size: int = 16, *, sharded: bool = False, parts: int = 1) -> float | None:
    """Argmax next-token accuracy over every labelled (gpt) position; None if there is none.

    ``sharded``: the model is FSDP-wrapped, so only its root forward gathers the root's parameters (the
    embedding, final norm and head); that forward computes full-vocabulary logits. ``parts`` > 1 (not sharded):
    the batches are shared out among as many Python threads, the caller's intra-op threads divided among them,
    computed side by side: each batch is computed alone, so the counts are those of one thread unless a matmul
    rounds otherwise on fewer intra-op threads (the CPU default's counts and logits measured the same).
    """
    if len(dataset) == 0:
        return None
    model.eval()
    collate = RightPadCollator(pad_token_id)
    order = sorted(range(len(dataset)), key=lambda i: len(dataset[i]["input_ids"]))
    starts = range(0, len(order), batch_size)
    device = next(model.parameters()).device

    def count(share: Sequence[int]) -> tuple[int, int]:
        correct = total = 0
        for start in share:
            batch = collate([dataset[i] for i in order[start:start + batch_size]])
            input_ids, labels = batch["input_ids"].to(device), batch["labels"].to(device)
            if sharded:
                targets = labels[:, 1:]
                keep = targets != IGNORE_INDEX
                predictions, targets = model(input_ids=input_ids).logits[:, :-1][keep].argmax(-1), targets[keep]
            else:
                # Project only labelled positions: a full-vocabulary logits tensor would dwarf the batch.
                logits, targets = head_at_labels(model, {"input_ids": input_ids, "labels": labels})
                predictions = logits.argmax(-1)
            correct += int((predictions == targets).sum())
            total += len(targets)
        return correct, total

    if parts > 1 and not sharded and len(starts) > 1:
        n = min(parts, len(starts))
        threads = PartThreads(n, max(1, torch.get_num_threads() // n))
        try:
            counts = threads.map([functools.partial(torch.no_grad()(count), starts[i::threads.parts])
                                  for i in range(threads.parts)])
        finally:
            threads.close()
    else:
        counts = [count(starts)]
    correct, total = map(sum, zip(*counts))
    return correct / total if total else None


def _checkpointing(enabled: bool) -> dict:
    """Activation (gradient) checkpointing, under the name this transformers release takes (newer ones renamed
    ``gradient_checkpointing`` to ``activation_checkpointing`` and warn on the old name); nothing when off."""
    if not enabled:
        return {}
    names = {f.name for f in dataclasses.fields(TrainingArguments)}
    return {"activation_checkpointing" if "activation_checkpointing" in names else "gradient_checkpointing": True}


def _training_arguments(settings: TrainSettings, checkpoints: Path, seed: int) -> TrainingArguments:
    bf16 = use_bf16(settings.bf16, settings.bf16_when_faster)
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
        seed=seed,
        logging_steps=settings.logging_steps,
        save_strategy="steps",
        save_steps=settings.save_steps,
        save_total_limit=settings.save_total_limit,
        bf16=bf16,
        # bf16 without a GPU is CPU autocast (AMX/AVX512-BF16 matmuls); transformers asks for use_cpu then.
        use_cpu=bf16 and not torch.cuda.is_available(),
        torch_compile=settings.torch_compile is CompileMode.full,  # regional: compiled_blocks, in place
        tf32=True if settings.tf32 and torch.cuda.is_available() else None,  # a GPU setting: no-op elsewhere
        **_checkpointing(settings.gradient_checkpointing),
        report_to=list(settings.report_to) or "none",
        dataloader_num_workers=settings.dataloader_num_workers,
        include_num_input_tokens_seen="non_padding",
        remove_unused_columns=False,
        dataloader_pin_memory=False,  # nothing to pin for on a CPU; on a GPU the gain is negligible here
    )


class _Compose(TrainerCallback):
    """After every optimizer step, the joined rows written anew from their parts (`ComposedRows.compose`)."""

    def __init__(self, rows: ComposedRows, weight: torch.Tensor):
        self.rows, self.weight = rows, weight

    def on_optimizer_step(self, args, state, control, **kwargs):
        self.rows.compose(self.weight)


@contextlib.contextmanager
def composed_rows(trainer: Trainer, tokenizer: PreTrainedTokenizerBase):
    """While ``trainer`` trains a model built with ``newlines=composed`` (its config's ``composed_newlines``),
    keep its joined rows composed (`ComposedRows`): each joined row's gradient goes to its word's and the
    newline's rows, and after every optimizer step the joined rows are written anew from them. Other models:
    nothing."""
    model = trainer.model
    if not getattr(model.config, "composed_newlines", False):
        yield
        return
    if trainer.is_fsdp_enabled:
        raise ValueError("newlines=composed is not supported with train.accelerate_config (FSDP shards the rows)")
    rows, weight = ComposedRows.of(tokenizer), model.get_input_embeddings().weight
    hook = weight.register_hook(rows.gradient)
    # With Muon the rows are written right after the AdamW groups' step (the embedding's), while the part threads
    # take Muon's (`MuonAdamW.meanwhile`): the same rows, outside the time between two steps.
    optimizer = trainer.optimizer if isinstance(trainer.optimizer, MuonAdamW) else None
    compose = functools.partial(rows.compose, weight)
    callback = _Compose(rows, weight)
    if optimizer is not None:
        optimizer.meanwhile.append(compose)
    else:
        trainer.add_callback(callback)
    try:
        yield
    finally:
        hook.remove()
        if optimizer is not None:
            optimizer.meanwhile.remove(compose)
        else:
            trainer.remove_callback(callback)


@contextlib.contextmanager
def _main_thread_alone(enabled: bool):
    """While the batch's parts and Muon's step run on the part threads, the calling thread's own work (clipping, the
    AdamW part, collation) on one intra-op thread: an idle intra-op thread of the caller's spins a while after each
    of its parallel kernels, on a core a part thread needs (README, Speed). The same numbers: the element-wise
    kernels and norms involved compute alike on one thread and two."""
    threads = torch.get_num_threads()
    if enabled:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


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
    seed: int = 0,
    max_length: int = 2048,
    callbacks: Sequence[TrainerCallback] = (),
) -> TrainResult:
    """Fine-tune ``model`` on ``conversations`` (loss on gpt turns), resuming from the last checkpoint in
    ``output_dir`` if there is one, and save the final model to ``output_dir/model``.

    ``seed`` seeds the Trainer and the held-out split; a conversation longer than ``max_length`` tokens is
    dropped or truncated (``settings.long_conversations``) and counted. With ``"mlflow"`` in ``settings.report_to``, transformers' MLflowCallback logs the
    Trainer's arguments as params and ``loss``, ``learning_rate``, ``grad_norm`` ... by step into the active
    run (or the run ``MLFLOW_RUN_ID`` names). A callback with a ``bind`` method gets the trainer before training
    starts (`benchmarks/bench_train.py`'s ``--switch`` flips its settings between steps).
    """
    threads = torch.get_num_threads()
    if settings.torch_threads is not None:
        torch.set_num_threads(settings.torch_threads)
    try:
        return _finetune(model, tokenizer, fmt, conversations, settings, Path(output_dir), seed, max_length, callbacks)
    finally:
        torch.set_num_threads(threads)  # jobs sharing a process (Hydra's basic launcher) keep their own


def _finetune(model, tokenizer, fmt, conversations, settings, output_dir, seed, max_length, callbacks) -> TrainResult:
    # Checkpoints are many and large: the final model is logged once by the caller instead.
    os.environ["HF_MLFLOW_LOG_ARTIFACTS"] = "FALSE"
    checkpoints = output_dir / CHECKPOINTS_DIR
    checkpoints.mkdir(parents=True, exist_ok=True)

    train_part, eval_part = split_eval(conversations, settings.eval_fraction, seed)
    with bulk_building():  # a list of token ids, and of labels, for each conversation
        train_data = tokenize_conversations(tokenizer, fmt, train_part, max_length, settings.long_conversations)
        eval_data = tokenize_conversations(tokenizer, fmt, eval_part, max_length, settings.long_conversations,
                                           "held-out")
    if len(train_data) == 0:
        raise ValueError(f"no training conversation fits max_length={max_length} "
                         f"({train_data.dropped} dropped)")

    with dynamo_environment():
        args = _training_arguments(settings, checkpoints, seed)  # bf16 decided once: autocast and Muon's precision
        trainer = (_PackingTrainer if settings.packing else _Trainer)(
            model=model,
            args=args,
            train_dataset=train_data,
            data_collator=RightPadCollator(tokenizer.pad_token_id,
                                           attention_mask=not settings.packing or settings.position_stretch > 1,
                                           pad_to_multiple_of=settings.pad_to_multiple_of),
            processing_class=tokenizer,
            callbacks=list(callbacks),
            optimizers=(build_optimizer(settings.optimizer, model, settings.learning_rate, settings.weight_decay,
                                        ns_dtype=torch.bfloat16 if settings.muon_bf16 and args.bf16 else torch.float32),
                        None),
        )
    trainer.position_stretch = settings.position_stretch
    trainer.labelled_logits = settings.labelled_logits
    trainer.labelled_last_layer = settings.labelled_last_layer
    if settings.labelled_last_layer:
        reason = not_cut(model.base_model, settings.torch_compile is CompileMode.stacked)
        if reason:
            log.warning("train.labelled_last_layer: %s: its last layer runs at every position", reason)
    threads = torch.get_num_threads()
    # On fewer threads than parts the batch stays whole: parts one after the other measured 0.97x (README, Speed).
    side_by_side = settings.batch_threads > 1 and threads >= settings.batch_threads
    if side_by_side:
        trainer.part_threads = PartThreads(settings.batch_threads, threads // settings.batch_threads,
                                           compile_settings if settings.torch_compile.blocks
                                           else contextlib.nullcontext)
        if isinstance(trainer.optimizer, MuonAdamW):  # its step shared out among the same threads
            trainer.optimizer.side_by_side = trainer.part_threads
            trainer.optimizer.meanwhile.append(trainer.fetch_ahead)  # the next batch, during Muon's step
    if any(isinstance(c, ProgressCallback) for c in trainer.callback_handler.callbacks):
        trainer.remove_callback(ProgressCallback)
        trainer.add_callback(BarProgress)
    for callback in callbacks:  # a callback that steers the trainer itself between steps (bench_train's --switch)
        if callable(getattr(callback, "bind", None)):
            callback.bind(trainer)
    resume = get_last_checkpoint(str(checkpoints))
    if resume:
        log.info("resuming from %s", resume)
    started = time.perf_counter()
    try:
        with compiled_blocks(model, settings.torch_compile, release_gil=side_by_side), \
                composed_rows(trainer, tokenizer), _main_thread_alone(side_by_side), walked_once():
            output = trainer.train(resume_from_checkpoint=resume)
    finally:
        if trainer.part_threads:
            if isinstance(trainer.optimizer, MuonAdamW):
                trainer.optimizer.side_by_side = None
                trainer.optimizer.meanwhile.remove(trainer.fetch_ahead)
            trainer.part_threads.close()
            trainer.part_threads = None
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
                              sharded=trainer.is_fsdp_enabled, parts=settings.batch_threads if side_by_side else 1)
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
        truncated=train_data.truncated + eval_data.truncated,
        resumed_from=resume,
        parameters=model.num_parameters(),
    )


def _real_token_fraction(trainer: Trainer) -> float:
    # Trainer counts 6 * (non-embedding parameters) FLOPs for every token it computes, padding included,
    # so total_flos gives the tokens computed over the whole run (restored on resume, summed over ranks).
    per_token = 6 * trainer.model.num_parameters(exclude_embeddings=True)
    computed = trainer.state.total_flos / per_token if per_token else 0
    return trainer.state.num_input_tokens_seen / computed if computed else 0.0
