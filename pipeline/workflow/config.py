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
from dataclasses import MISSING as MISSING_FIELD, dataclass, field, fields, is_dataclass, make_dataclass
from enum import Enum
from typing import Any, Optional, get_type_hints

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING, DictConfig, OmegaConf

from pipeline.core.checks import SettingError
from pipeline.core.variants import (ALIASES, BASELINES, BY_NAME, DIRECTIONS, MODES, REFERENCE, SWITCHES, VARIANT_ROWS,
                                    UndefinedCombination, Variant, VariantError, check, variant_for)
from pipeline.lm.model_settings import ModelKind, ModelSettings
from pipeline.lm.training.settings import CompileMode, TrainSettings
from pipeline.workflow.data_build import DataSettings, repeated_worlds_error, world_files
from pipeline.workflow.paper_data import ResolvedFile
from pipeline.workflow.paper_data import PaperDataError
from pipeline.workflow.evaluation import EvalSettings
from pipeline.workflow.tracking import default_tracking_uri

# The config's choices, from the variants table (an Enum is what a structured config checks a choice with).
Direction = Enum("Direction", {name: name for name in DIRECTIONS}, type=str)
Mode = Enum("Mode", {name: name for name in MODES}, type=str)
Baseline = Enum("Baseline", {name: name for name in ("cogmap", *BASELINES)}, type=str)


@dataclass
class TrackingConfig:
    root: str = "outputs"
    uri: Optional[str] = None  # default: sqlite under root
    experiment: str = "cogmap"


@dataclass
class _JobConfig:
    direction: Direction = Direction.bwd
    mode: Mode = Mode.optimal
    baseline: Baseline = Baseline.cogmap
    seed: int = 0
    # torch threads for this job (null: torch's default). Two 1-thread jobs beat one 2-thread job on small models.
    threads: Optional[int] = None
    # In a sweep grid, skip cells that are undefined (dfs in the optimal setting) instead of failing.
    skip_undefined: bool = False
    data: DataSettings = field(default_factory=DataSettings)
    model: ModelSettings = field(default_factory=ModelSettings)
    train: TrainSettings = field(default_factory=TrainSettings)
    eval: EvalSettings = field(default_factory=EvalSettings)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)
    # Stable per-step working folders (checkpoints, partial eval records) for resuming; under tracking.root.
    work_dir: str = MISSING


def _run_config() -> type:
    """The job's whole config: `_JobConfig`'s fields with one boolean per map switch of the variants table
    (`SWITCHES`) after ``baseline``, each defaulting to the reference variant's. Its sections are the settings
    the code itself takes."""
    switches = [(name, bool, field(default=on)) for name, on in BY_NAME[REFERENCE].switches._asdict().items()]
    types = get_type_hints(_JobConfig)  # the annotations as types (this module's are strings)
    job = [(f.name, types[f.name], field(default=f.default) if f.default_factory is MISSING_FIELD else
            field(default_factory=f.default_factory)) for f in fields(_JobConfig)]
    at = 1 + next(i for i, (name, _, _) in enumerate(job) if name == "baseline")
    return make_dataclass("RunConfig", [*job[:at], *switches, *job[at:]])


RunConfig = _run_config()

_ON_OFF = {"on": True, "off": False}


def _preset(row: Variant) -> dict:
    """A variant's preset: the config-group choices that make it (a baseline keeps the reference's switches,
    which its texts ignore, so a command-line switch still has a group to override)."""
    switches = (row.switches or BY_NAME[REFERENCE].switches)._asdict()
    choices = [{"/baseline": "cogmap" if row.is_map else row.name},
               *({f"/{name}": "on" if on else "off"} for name, on in switches.items())]
    if row.reachable_only:
        choices.append({"override /mode": "reachable"})
    return {"defaults": choices}


def register_configs() -> None:
    """Register the schema (so `defaults: [run_schema]` validates every composed config), the config groups
    and variant presets the variants table defines, and the resolvers.

    Groups: ``direction``, ``mode``, ``baseline`` and one ``on``/``off`` group per map switch, each option
    setting its key; ``variant``: one preset per row of the table (and its aliases) choosing those groups.
    A preset's choices sit in its own defaults list, so a group given on the command line wins over them.
    """
    store = ConfigStore.instance()
    store.store(name="run_schema", node=RunConfig)
    groups = {"direction": {d: d for d in DIRECTIONS}, "mode": {m: m for m in MODES},
              "baseline": {b: b for b in Baseline.__members__}, **{name: _ON_OFF for name in SWITCHES}}
    for group, options in groups.items():
        for option, value in options.items():
            store.store(group=group, name=option, node={group: value}, package="_global_")
    for row in VARIANT_ROWS:
        store.store(group="variant", name=row.name, node=_preset(row), package="_global_")
    for alias, name in ALIASES.items():
        store.store(group="variant", name=alias, node={"defaults": [name]}, package="_global_")
    OmegaConf.register_new_resolver("tracking_uri", default_tracking_uri, replace=True)


class ConfigError(ValueError):
    """A configuration that cannot run, found before any work starts."""


class UndefinedCell(ConfigError):
    """A grid cell the paper does not define (dfs in the optimal setting)."""


@dataclass(frozen=True)
class JobSettings:
    """A validated config as the steps take it: the variant and each section's settings."""

    variant: str
    data: DataSettings
    model: ModelSettings
    train: TrainSettings
    eval: EvalSettings
    files: dict[str, ResolvedFile | None]   # the splits' world files, resolved (None: generated)


def variant_name(cfg: DictConfig) -> str:
    """The variant the switches describe (a map variant or a baseline); raises ConfigError if none."""
    try:
        return variant_for(Baseline(cfg.baseline).value, {name: cfg[name] for name in SWITCHES})
    except VariantError as error:
        raise ConfigError(str(error)) from None


def _section(cfg: DictConfig, name: str):
    """One section's settings, built (and so checked) from the config; ConfigError naming the bad value."""
    try:
        return OmegaConf.to_object(cfg[name])
    except SettingError as error:
        raise ConfigError(f"{name}.{error}") from None


def unknown_keys(cfg: DictConfig) -> list[str]:
    """Keys the schema does not have. A plain typo fails at compose time, but ``+key=value`` adds a key to the
    structured config whatever it is, so ``+trian.lr=5`` would run with the key ignored."""
    def walk(node, defaults, prefix: str) -> list[str]:
        if not (isinstance(node, DictConfig) and is_dataclass(defaults)):
            return []
        known = {f.name for f in fields(defaults)}
        return [found for key in node for found in
                ([prefix + str(key)] if key not in known else walk(node[key], getattr(defaults, key), f"{prefix}{key}."))]
    return walk(cfg, RunConfig(), "")


def validate(cfg: DictConfig) -> JobSettings:
    """Build and check every section (each value is checked once, by its settings class), then what needs
    several sections or the file system. Raises ConfigError naming the bad value."""
    unknown = unknown_keys(cfg)
    if unknown:
        raise ConfigError(f"unknown config key(s) {', '.join(unknown)} (added with '+'?); allowed: the keys that "
                          "`python -m pipeline.run --cfg job` prints")
    variant = variant_name(cfg)
    try:
        check(Direction(cfg.direction).value, variant, Mode(cfg.mode).value)
    except UndefinedCombination as error:
        raise UndefinedCell(str(error)) from None
    data, model, train, evaluation = (_section(cfg, name) for name in ("data", "model", "train", "eval"))
    if evaluation.n_worlds is not None and evaluation.n_worlds > data.n_test:
        raise ConfigError(f"eval.n_worlds={evaluation.n_worlds}: the test split has data.n_test={data.n_test} worlds; "
                          f"allowed: 1..{data.n_test} or null for all")
    if evaluation.curve and not train.log_checkpoints:
        raise ConfigError("eval.curve=true needs train.log_checkpoints=true (the curve evaluates logged checkpoints)")
    if train.torch_compile is not CompileMode.none:
        missing = [what for what, ok in ((f"a C++ compiler ({_cxx_name()!r} is not on PATH)", cxx_compiler()),
                                         (f"the Python headers ({PYTHON_H} is missing)", PYTHON_H.is_file()))
                   if not ok]
        if missing and not _cuda_visible():
            raise ConfigError(
                f"train.torch_compile={train.torch_compile.value}: torch.compile on a CPU builds "
                f"its kernels as Python extensions and needs {' and '.join(missing)}; install them (Debian: apt "
                "install g++ python3-dev), point $CXX at a compiler, or set train.torch_compile=none"
            )
    try:
        files = world_files(data)
    except (FileNotFoundError, PaperDataError) as error:
        raise ConfigError(str(error)) from None
    if files["test"] is not None:
        _check_test_file(data, model, files["test"])
    if model.kind is ModelKind.hf:
        path = Path(model.path).expanduser()
        if not path.is_dir() or not (path / "config.json").is_file() or not any(path.glob("*.safetensors")):
            raise ConfigError(f"model.path={model.path!r}: expected a local directory with config.json and "
                              "*.safetensors weights (models load from safetensors only)")
    return JobSettings(variant, data, model, train, evaluation, files)


def _check_test_file(data: DataSettings, model: ModelSettings, found: ResolvedFile) -> None:
    """The test file exists, holds data.n_test worlds, and (for a model trained from scratch, whose
    vocabulary holds the cells of data.frame) no world reaches outside the frame."""
    from pipeline.core.world import WorldError, load_worlds

    try:
        worlds = load_worlds(found.path)
    except WorldError as error:
        raise ConfigError(f"data.test_file={data.test_file!r}: {error}") from None
    if len(worlds) < data.n_test:
        raise ConfigError(f"data.n_test={data.n_test} but data.test_file={data.test_file!r} holds {len(worlds)} "
                          f"worlds; allowed: 1..{len(worlds)}")
    error = repeated_worlds_error(f"data.test_file={data.test_file!r}", worlds[: data.n_test])
    if error:
        raise ConfigError(error)
    if model.kind is not ModelKind.scratch:
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


def config_hash(*parts: Any) -> str:
    """A short stable hash of JSON-able parts (OmegaConf nodes are resolved first)."""
    plain = [OmegaConf.to_container(p, resolve=True, enum_to_str=True) if isinstance(p, DictConfig) else p for p in parts]
    payload = json.dumps(plain, sort_keys=True, default=str, separators=(",", ":"))
    return hashlib.sha256(payload.encode()).hexdigest()[:16]
