"""The training settings: one schema, used by the trainer and, unchanged, as the Hydra config's ``train`` node.

Its defaults are the base every ``conf/train/*.yaml`` preset starts from; a preset lists only what differs.
Values are checked once, when the settings are built (``OmegaConf.to_object`` builds them from the config).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from enum import Enum
from typing import Optional

from pipeline.core.checks import SettingError, require

REPORT_TARGETS = ("mlflow",)
SCHEDULERS = ("cosine", "linear", "constant", "constant_with_warmup", "cosine_with_restarts", "polynomial")
# What becomes of a conversation longer than the context (model.max_length): left out, or cut to the context and
# trained on the targets left (the paper's code: its tokenizer truncates).
LONG_CONVERSATIONS = ("drop", "truncate")
# The most parts a batch is cut into (`TrainSettings.batch_threads`): with more, the order in which their
# gradients add up would vary between runs.
MAX_BATCH_PARTS = 2
# Trainer's AdamW, or Muon for the decoder layers' matrices with AdamW for the rest (pipeline/lm/training/optim.py).
OPTIMIZERS = ("adamw", "muon")


class CompileMode(str, Enum):
    """What torch.compile (inductor) compiles."""

    none = "none"
    regional = "regional"   # each repeated block (decoder layer) in place; one graph shared by the layers
    stacked = "stacked"     # the repeated blocks, in place, as one graph that runs them in turn
    full = "full"           # the whole model, through Trainer

    @property
    def blocks(self) -> bool:
        """Whether `pipeline.lm.training.compile.compiled_blocks` compiles the model's repeated blocks."""
        return self in (CompileMode.regional, CompileMode.stacked)


@dataclass
class TrainSettings:
    """Everything that decides a fine-tuning run besides the model, the data and the seed.

    ``max_steps`` (optimizer steps) wins over ``num_epochs`` when set. ``per_device_batch_size`` counts
    sequences; the effective batch is it times ``gradient_accumulation_steps`` times the number of devices.
    ``eval_fraction`` of the conversations is held out for a token-accuracy eval. ``pad_to_multiple_of``
    rounds each batch's width up: a few distinct shapes instead of one per length, so the kernels oneDNN
    builds per shape (bf16 on a CPU) are built a few times, not hundreds. ``packing`` groups batches by
    length and sends no attention mask (see `pipeline.lm.training.batches`). ``torch_compile``: see
    `CompileMode`; on a CPU, compiling needs a C++ compiler and the Python headers. ``bf16``: bf16 mixed
    precision on a GPU; on a CPU, autocast where the CPU has bf16 hardware, and with ``bf16_when_faster`` only
    where its bf16 matmuls measure at least `BF16_MIN_SPEEDUP` times fp32's (`pipeline.lm.training.compile.use_bf16`).
    ``accelerate_config``: train under ``accelerate launch --config_file <it>`` (distributed, e.g. FSDP) in a
    subprocess. ``log_checkpoints``: the finetune step also logs every checkpoint's weights (the eval
    step's adaptation curve evaluates them). ``long_conversations`` (`LONG_CONVERSATIONS`): a conversation
    longer than the context is dropped (the default: a model trained from scratch learns nothing from an
    answer cut off mid-map) or truncated to it, as the paper's code does (``train=paper``).
    """

    max_steps: Optional[int] = None
    num_epochs: float = 1.0
    per_device_batch_size: int = 16
    gradient_accumulation_steps: int = 1
    learning_rate: float = 1e-3
    lr_scheduler_type: str = "cosine"
    warmup_ratio: float = 0.03
    weight_decay: float = 0.0
    max_grad_norm: float = 1.0
    packing: bool = True
    pad_to_multiple_of: int = 8
    logging_steps: int = 10
    save_steps: int = 500
    save_total_limit: Optional[int] = 2
    bf16: bool = False
    tf32: bool = False
    gradient_checkpointing: bool = False
    torch_compile: CompileMode = CompileMode.none
    report_to: list[str] = field(default_factory=lambda: ["mlflow"])
    dataloader_num_workers: int = 0
    torch_threads: Optional[int] = None
    eval_fraction: float = 0.0
    accelerate_config: Optional[str] = None
    log_checkpoints: bool = False
    long_conversations: str = field(default="drop", metadata={"hash_if_set": True})
    # Faster training where a CPU's bf16 is slow; it changes the numbers (README, Speed).
    bf16_when_faster: bool = field(default=False, metadata={"hash_if_set": True})
    # `OPTIMIZERS` (the same learning rate and weight decay for both); not with accelerate_config (FSDP).
    optimizer: str = field(default="adamw", metadata={"hash_if_set": True})
    # Muon's Newton-Schulz iterations in bf16 (as the reference implementation runs them) where training runs in
    # bf16; fp32 otherwise. Off with any other optimizer or without bf16. It changes the numbers (README, Speed).
    muon_bf16: bool = field(default=False, metadata={"hash_if_set": True})
    # Training conversations see randomized, stretched position ids (`batches.stretched_positions`; 1: plain
    # positions); decoding keeps plain ones. Not in the paper (docs/extrapolation.md).
    position_stretch: float = field(default=1.0, metadata={"hash_if_set": True})
    # Each micro-batch cut into this many parts of consecutive rows, computed side by side by as many Python
    # threads where the job has that many torch threads (else whole); the same training, rounded otherwise than
    # the uncut batch (pipeline/lm/training/parts.py; README, Speed).
    batch_threads: int = field(default=1, metadata={"hash_if_set": True})
    # The output head and the loss computed at the labelled (trained) positions only, not at every position: the
    # same loss and gradients, rounded otherwise (pipeline/lm/training/trainer.py: labelled_loss; README, Speed).
    labelled_logits: bool = field(default=False, metadata={"hash_if_set": True})
    # With labelled_logits, the last decoder layer computed only from the first position a batch trains on (its
    # keys and values everywhere): the same loss and gradients, rounded otherwise; Llama with eager attention, not
    # compiled stacked (pipeline/lm/training/last_layer.py; README, Speed). Off without labelled_logits.
    labelled_last_layer: bool = field(default=False, metadata={"hash_if_set": True})

    def __post_init__(self) -> None:
        self.report_to = [self.report_to] if isinstance(self.report_to, str) else list(self.report_to)
        self.torch_compile = _enum(CompileMode, self.torch_compile, "torch_compile")
        if self.max_steps is not None:
            require(isinstance(self.max_steps, int) and self.max_steps > 0, "max_steps", self.max_steps,
                    "a positive integer, or null to train num_epochs")
        require(self.num_epochs > 0, "num_epochs", self.num_epochs, "a positive number")
        for name in ("per_device_batch_size", "gradient_accumulation_steps", "logging_steps", "save_steps",
                     "pad_to_multiple_of"):
            value = getattr(self, name)
            require(isinstance(value, int) and value > 0, name, value, "a positive integer")
        require(self.learning_rate > 0, "learning_rate", self.learning_rate, "a positive number")
        require(self.lr_scheduler_type in SCHEDULERS, "lr_scheduler_type", self.lr_scheduler_type,
                f"one of {', '.join(SCHEDULERS)}")
        require(0 <= self.warmup_ratio < 1, "warmup_ratio", self.warmup_ratio, "a ratio in [0, 1)")
        require(self.weight_decay >= 0, "weight_decay", self.weight_decay, "a number >= 0")
        require(self.max_grad_norm > 0, "max_grad_norm", self.max_grad_norm, "a positive number")
        require(self.save_total_limit is None or self.save_total_limit > 0, "save_total_limit",
                self.save_total_limit, "a positive integer, or null to keep every checkpoint")
        require(set(self.report_to) <= set(REPORT_TARGETS), "report_to", self.report_to,
                f"a subset of {list(REPORT_TARGETS)} (empty: report nowhere)")
        require(self.dataloader_num_workers >= 0, "dataloader_num_workers", self.dataloader_num_workers,
                "an integer >= 0")
        require(self.torch_threads is None or self.torch_threads > 0, "torch_threads", self.torch_threads,
                "a positive integer, or null to leave torch's setting")
        require(0 <= self.eval_fraction < 1, "eval_fraction", self.eval_fraction, "a fraction in [0, 1)")
        require(self.optimizer in OPTIMIZERS, "optimizer", self.optimizer, f"one of {', '.join(OPTIMIZERS)}")
        require(self.optimizer == "adamw" or self.accelerate_config is None, "optimizer", self.optimizer,
                "adamw when accelerate_config is set (FSDP shards the matrices Muon orthogonalizes)")
        if self.optimizer != "muon" or not self.bf16:  # nothing to set without Muon or bf16 (train=cpu sets it)
            self.muon_bf16 = False
        require(self.position_stretch >= 1, "position_stretch", self.position_stretch,
                "a number >= 1 (1: plain positions)")
        require(isinstance(self.batch_threads, int) and 1 <= self.batch_threads <= MAX_BATCH_PARTS,
                "batch_threads", self.batch_threads, f"an integer from 1 to {MAX_BATCH_PARTS} (with more parts "
                "the order their gradients add up in would vary between runs)")
        require(self.batch_threads == 1 or self.accelerate_config is None, "batch_threads", self.batch_threads,
                "1 with accelerate_config (distributed training splits batches its own way)")
        require(not self.labelled_logits or self.accelerate_config is None, "labelled_logits", self.labelled_logits,
                "false with accelerate_config (a sharded model computes its head inside its own forward)")
        if not self.labelled_logits:  # it cuts labelled_logits' forward: nothing to cut without it
            self.labelled_last_layer = False
        require(self.long_conversations in LONG_CONVERSATIONS, "long_conversations", self.long_conversations,
                f"one of {', '.join(LONG_CONVERSATIONS)}")

    @classmethod
    def from_dict(cls, values: dict) -> "TrainSettings":
        """Settings from a plain mapping; unknown keys are an error, not ignored."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise SettingError(f"unknown train settings {unknown}; allowed: {sorted(known)}")
        return cls(**values)

    def to_dict(self) -> dict:
        """Plain JSON-ready values (enums as their strings)."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}


def _enum(kind: type[Enum], value: object, name: str):
    try:
        return kind(value.value if isinstance(value, Enum) else value)
    except ValueError:
        raise SettingError(f"{name}={value!r} is not allowed; expected one of "
                           f"{', '.join(m.value for m in kind)}") from None


def _plain(value: object) -> object:
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value
