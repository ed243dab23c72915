"""The job's configuration: structured-config schemas (typos fail at compose time) and the checks
that need several fields at once (impossible combinations fail before any work)."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import sysconfig
from pathlib import Path
from dataclasses import dataclass, field
from enum import Enum
from typing import Any, Optional

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from pipeline.core.texts import MAP_VARIANTS, PAPER_MAP_VARIANTS, PROMPTS
from pipeline.workflow.tracking import default_tracking_uri

# transformers' attention kernels (model.attn_implementation). On the 2-core AMX CPU, SDPA and "eager" (two
# batched matmuls and a softmax) train heads of 64 in bf16 at about the same speed; eager is faster for one
# head of 128. "flash_attention_2" needs the flash-attn package and a GPU.
ATTENTION_IMPLEMENTATIONS = ("sdpa", "eager", "flash_attention_2")
LOG_MODEL_CHOICES = ("transformers", "reference")


class Direction(str, Enum):
    fwd = "fwd"
    bwd = "bwd"


class Mode(str, Enum):
    optimal = "optimal"
    reachable = "reachable"


class Baseline(str, Enum):
    cogmap = "cogmap"
    none = "none"
    cot = "cot"
    dfs = "dfs"


class CompileMode(str, Enum):
    none = "none"
    regional = "regional"   # each repeated block (decoder layer) compiled in place; one graph for all of them
    full = "full"


class ModelKind(str, Enum):
    scratch = "scratch"
    hf = "hf"


class Backend(str, Enum):
    hf = "hf"
    vllm = "vllm"


@dataclass
class DataConfig:
    train_size_x: list[int] = field(default_factory=lambda: [2, 10])
    train_size_y: list[int] = field(default_factory=lambda: [2, 10])
    test_size_x: list[int] = field(default_factory=lambda: [2, 20])
    test_size_y: list[int] = field(default_factory=lambda: [2, 20])
    frame: int = 20
    p_pit: list[float] = field(default_factory=lambda: [0.1, 0.5])
    n_train: int = 50_000
    n_test: int = 3_000
    # The paper's released test worlds instead of generated ones (a path to a JSONL in its schema).
    test_file: Optional[str] = None
    seed: int = 0
    workers: int = 2


@dataclass
class ChatFormatConfig:
    human_prefix: str = "<human>"
    gpt_prefix: str = "<gpt>"
    turn_end: str = "</s>"
    bos: str = "<s>"


@dataclass
class ModelConfig:
    kind: ModelKind = ModelKind.scratch
    # kind=hf: a local directory (or hub name on a machine that can reach one) of a causal LM.
    path: Optional[str] = None
    hidden_size: int = 128
    num_layers: int = 4
    num_heads: int = 2
    intermediate_size: int = 512
    max_length: int = 2048
    dtype: str = "float32"
    attn_implementation: str = "sdpa"   # sdpa | eager | flash_attention_2
    trust_remote_code: bool = False
    chat_format: ChatFormatConfig = field(default_factory=ChatFormatConfig)
    # What the model is prompted with (texts.PROMPTS): "paper" (instruction, "OK", task) or "task" (the task
    # turn alone: for models trained from scratch, which cannot use the fixed English instruction).
    prompt: str = "paper"
    # How the finetuned model is logged as an MLflow model: "transformers" (the flavour, weights copied) or
    # "reference" (a logged model pointing at the finetune run's model/ artifacts: for large models).
    log_model: str = "transformers"


@dataclass
class TrainConfig:
    max_steps: int = 1000
    per_device_batch_size: int = 16
    gradient_accumulation_steps: int = 1
    learning_rate: float = 1e-3
    lr_scheduler_type: str = "cosine"
    warmup_ratio: float = 0.03
    weight_decay: float = 0.0
    max_length: int = 2048
    packing: bool = True
    pad_to_multiple_of: int = 8
    logging_steps: int = 10
    save_steps: int = 100
    save_total_limit: Optional[int] = None
    bf16: bool = False
    torch_compile: CompileMode = CompileMode.none   # none | regional | full
    max_grad_norm: float = 1.0
    num_epochs: float = 1.0
    report_to: list[str] = field(default_factory=lambda: ["mlflow"])
    dataloader_num_workers: int = 0
    torch_threads: Optional[int] = None
    eval_fraction: float = 0.02
    # Distributed training (paper scale): launch `accelerate launch --config_file ...` in a subprocess.
    accelerate_config: Optional[str] = None
    # Log every checkpoint's weights (not optimizer state) so eval can draw the adaptation curve.
    log_checkpoints: bool = False


@dataclass
class EvalConfig:
    # How many test worlds to evaluate (the first n of the test split); null = all.
    n_worlds: Optional[int] = None
    backend: Backend = Backend.hf
    batch_size: int = 32
    max_new_tokens: int = 4096
    max_steps: int = 200
    # Figure 3: evaluate each logged checkpoint on the first `curve_worlds` test worlds.
    curve: bool = False
    curve_worlds: int = 50


@dataclass
class TrackingConfig:
    root: str = "outputs"
    uri: Optional[str] = None  # default: sqlite under root
    experiment: str = "cogmap"


@dataclass
class RunConfig:
    direction: Direction = Direction.bwd
    mode: Mode = Mode.optimal
    baseline: Baseline = Baseline.cogmap
    all_moves: bool = True
    marking: bool = True
    backtrack: bool = True
    named: bool = False     # not in the paper: `From (x, y):` before each expanded state's neighbours
    seed: int = 0
    # torch threads for this job (null: torch's default). Two 1-thread jobs beat one 2-thread job on small models.
    threads: Optional[int] = None
    # In a sweep grid, skip cells that are undefined (dfs in the optimal setting) instead of failing.
    skip_undefined: bool = False
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    eval: EvalConfig = field(default_factory=EvalConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    # Stable per-step working folders (checkpoints, partial eval records) for resuming; under tracking.root.
    work_dir: str = MISSING


def register_configs() -> None:
    """Register the schema (so `defaults: [run_schema]` validates every composed config) and resolvers."""
    ConfigStore.instance().store(name="run_schema", node=RunConfig)
    OmegaConf.register_new_resolver("tracking_uri", default_tracking_uri, replace=True)


class ConfigError(ValueError):
    """A configuration that cannot run, found before any work starts."""


class UndefinedCell(ConfigError):
    """A grid cell the paper does not define (dfs in the optimal setting)."""


def variant_name(cfg: DictConfig | RunConfig) -> str:
    """The variant the switches describe (a SPEC 3 map variant or a baseline); raises ConfigError if none."""
    baseline = Baseline(cfg.baseline).value
    named = bool(cfg.get("named", False))
    if baseline != Baseline.cogmap.value:
        if named:
            raise ConfigError(f"named=on names the expanded states of a cognitive map; baseline={baseline} has "
                              "none. Allowed: named=off, or a map variant (baseline=cogmap)")
        return baseline
    switches = (bool(cfg.all_moves), bool(cfg.marking), bool(cfg.backtrack), named)
    for name, value in MAP_VARIANTS.items():
        if tuple(value) == switches:
            return name
    raise ConfigError(
        f"marking=on needs all_moves=on (got all_moves={cfg.all_moves}, marking={cfg.marking}): "
        f"'cut' labels exist only where all four neighbours are listed. Allowed switch settings: "
        + ", ".join(f"{n} (all_moves={a}, marking={m}, backtrack={b})"
                    for n, (a, m, b, _) in PAPER_MAP_VARIANTS.items())
    )


def validate(cfg: DictConfig) -> str:
    """Check what the schema cannot; return the variant name. Raises ConfigError naming the bad value."""
    variant = variant_name(cfg)
    if variant == Baseline.dfs.value and Mode(cfg.mode) is Mode.optimal:
        raise UndefinedCell("variant=dfs is defined only in the reachable setting (mode=reachable); got mode=optimal")
    data = cfg.data
    for name in ("train_size_x", "train_size_y", "test_size_x", "test_size_y"):
        lo, hi = _pair(data[name], f"data.{name}")
        if lo < 2 or hi < lo or hi > data.frame:
            raise ConfigError(f"data.{name}={[lo, hi]}: need 2 <= min <= max <= data.frame ({data.frame})")
    lo, hi = _pair(data.p_pit, "data.p_pit")
    if not 0.0 <= lo <= hi <= 1.0:
        raise ConfigError(f"data.p_pit={[lo, hi]}: need 0 <= min <= max <= 1")
    for name in ("n_train", "n_test", "workers"):
        if data[name] < 1:
            raise ConfigError(f"data.{name}={data[name]}: must be at least 1")
    if cfg.eval.n_worlds is not None and not 1 <= cfg.eval.n_worlds <= data.n_test:
        raise ConfigError(
            f"eval.n_worlds={cfg.eval.n_worlds}: the test split has data.n_test={data.n_test} worlds; "
            f"allowed: 1..{data.n_test} or null for all"
        )
    if cfg.train.max_steps < 1:
        raise ConfigError(f"train.max_steps={cfg.train.max_steps}: must be at least 1")
    if cfg.eval.curve and not cfg.train.log_checkpoints:
        raise ConfigError("eval.curve=true needs train.log_checkpoints=true (the curve evaluates logged checkpoints)")
    if cfg.model.log_model not in LOG_MODEL_CHOICES:
        raise ConfigError(f"model.log_model={cfg.model.log_model!r}: allowed: {', '.join(LOG_MODEL_CHOICES)}")
    if cfg.model.prompt not in PROMPTS:
        raise ConfigError(f"model.prompt={cfg.model.prompt!r}: allowed: {', '.join(PROMPTS)}")
    if cfg.model.attn_implementation not in ATTENTION_IMPLEMENTATIONS:
        raise ConfigError(f"model.attn_implementation={cfg.model.attn_implementation!r}: allowed: "
                          f"{', '.join(ATTENTION_IMPLEMENTATIONS)}")
    compile_mode = CompileMode(cfg.train.torch_compile)
    if compile_mode is not CompileMode.none:
        missing = [what for what, ok in ((f"a C++ compiler ({_cxx_name()!r} is not on PATH)", cxx_compiler()),
                                         (f"the Python headers ({PYTHON_H} is missing)", PYTHON_H.is_file()))
                   if not ok]
        if missing and not _cuda_visible():
            raise ConfigError(
                f"train.torch_compile={compile_mode.value}: torch.compile on a CPU builds "
                f"its kernels as Python extensions and needs {' and '.join(missing)}; install them (Debian: apt "
                "install g++ python3-dev), point $CXX at a compiler, or set train.torch_compile=none"
            )
    if ModelKind(cfg.model.kind) is ModelKind.hf and not cfg.model.path:
        raise ConfigError("model.kind=hf needs model.path: a local directory with a causal LM and its tokenizer")
    if data.test_file:
        _check_test_file(cfg)
    if ModelKind(cfg.model.kind) is ModelKind.hf:
        path = Path(cfg.model.path).expanduser()
        if not path.is_dir() or not (path / "config.json").is_file() or not any(path.glob("*.safetensors")):
            raise ConfigError(f"model.path={cfg.model.path!r}: expected a local directory with config.json and "
                              "*.safetensors weights (models load from safetensors only)")
    return variant


def _check_test_file(cfg: DictConfig) -> None:
    """The test file exists, holds data.n_test worlds, and (for a model trained from scratch, whose
    vocabulary holds the cells of data.frame) no world reaches outside the frame."""
    from pipeline.core.world import WorldError, load_worlds

    data = cfg.data
    path = Path(data.test_file).expanduser()
    if not path.is_file():
        raise ConfigError(f"data.test_file={data.test_file!r}: no such file; expected a JSONL of worlds in the paper's schema")
    try:
        worlds = load_worlds(path)
    except WorldError as error:
        raise ConfigError(f"data.test_file={data.test_file!r}: {error}") from None
    if len(worlds) < data.n_test:
        raise ConfigError(f"data.n_test={data.n_test} but data.test_file={data.test_file!r} holds {len(worlds)} "
                          f"worlds; allowed: 1..{len(worlds)}")
    if ModelKind(cfg.model.kind) is not ModelKind.scratch:
        return
    for index, world in enumerate(worlds[: data.n_test]):
        corner = (world.x0 + world.size_x - 1, world.y0 + world.size_y - 1)
        if min(world.x0, world.y0) < 0 or max(corner) >= data.frame:
            outside = corner if max(corner) >= data.frame else (world.x0, world.y0)
            needed = max(max(corner) + 1, data.frame)
            raise ConfigError(
                f"data.test_file={data.test_file!r}: test world {index} has the cell {outside} outside the "
                f"coordinates a model trained from scratch knows (data.frame={data.frame}: cells 0..{data.frame - 1} "
                f"on each axis); allowed: data.frame >= {needed} (and coordinates >= 0)")


PYTHON_H = Path(sysconfig.get_path("include")) / "Python.h"


def _cxx_name() -> str:
    # inductor's choice on a CPU: $CXX, else g++ (clang++ on macOS).
    return os.environ.get("CXX") or ("clang++" if sys.platform == "darwin" else "g++")


def cxx_compiler() -> str | None:
    """Path of the C++ compiler torch.compile (inductor) would build CPU kernels with, or None if missing."""
    return shutil.which(_cxx_name())


def _cuda_visible() -> bool:
    import torch

    return torch.cuda.is_available()


def _pair(value: Any, name: str) -> tuple:
    if len(value) != 2:
        raise ConfigError(f"{name}={list(value)}: expected [min, max]")
    return value[0], value[1]


def config_hash(*parts: Any) -> str:
    """A short stable hash of JSON-able parts (OmegaConf nodes are resolved first)."""
    plain = [OmegaConf.to_container(p, resolve=True, enum_to_str=True) if isinstance(p, DictConfig) else p for p in parts]
    payload = json.dumps(plain, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(payload.encode()).hexdigest()[:16]
