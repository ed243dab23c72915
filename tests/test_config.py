"""Every config group option, preset and sweep file composes; impossible combinations fail early."""

from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.global_hydra import GlobalHydra
from omegaconf import OmegaConf

from pipeline.config import ConfigError, UndefinedCell, register_configs, validate, variant_name
from pipeline.texts import MAP_VARIANTS

ROOT = Path(__file__).resolve().parents[1]
CONF, SWEEPS = ROOT / "conf", ROOT / "sweeps"
register_configs()


def _compose(overrides=(), name="config", sweeps=False, hydra_node=False):
    GlobalHydra.instance().clear()
    # As `--config-dir sweeps --config-name NAME`: the sweep file is primary, conf/ stays searchable.
    extra = [f"hydra.searchpath=[file://{CONF}]"] if sweeps else []
    with initialize_config_dir(str(SWEEPS if sweeps else CONF), version_base="1.3"):
        return compose(name, overrides=[*extra, *overrides], return_hydra_config=hydra_node)


def _options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF / group).glob("*.yaml"))


def test_default_job_is_bwd_marking_deadend_optimal():
    cfg = _compose()
    assert (cfg.direction.value, cfg.mode.value) == ("bwd", "optimal")
    assert validate(cfg) == "marking-deadend"


@pytest.mark.parametrize("group", ["direction", "mode", "baseline", "marking", "backtrack", "all_moves",
                                   "variant", "model", "data", "train", "eval", "tracking"])
def test_every_group_option_composes(group):
    for option in _options(group):
        cfg = _compose([f"{group}={option}"])
        OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)


@pytest.mark.parametrize("variant", list(MAP_VARIANTS) + ["none", "cot"])
def test_variant_presets_name_their_row(variant):
    assert validate(_compose([f"variant={variant}"])) == variant


def test_aliases_and_command_line_switches_win_over_presets():
    assert validate(_compose(["variant=marking"])) == "marking-deadend"
    assert validate(_compose(["variant=nomarking"])) == "no-marking"
    assert validate(_compose(["variant=no-marking", "marking=on"])) == "marking-deadend"
    assert validate(_compose(["variant=marking-deadend", "backtrack=off"])) == "no-backtrack"


def test_dfs_preset_is_reachable_and_optimal_dfs_is_refused():
    assert validate(_compose(["variant=dfs"])) == "dfs"
    with pytest.raises(UndefinedCell, match="mode=reachable"):
        validate(_compose(["variant=dfs", "mode=optimal"]))


def test_marking_without_all_moves_is_refused_naming_the_values():
    with pytest.raises(ConfigError, match="all_moves=False, marking=True"):
        variant_name(_compose(["variant=no-all", "marking=on"]))


@pytest.mark.parametrize("override, message", [
    ("data.train_size_x=[1,5]", "data.train_size_x"),
    ("data.test_size_y=[2,30]", "data.frame"),
    ("data.p_pit=[0.5,1.5]", "data.p_pit"),
    ("data.n_train=0", "data.n_train"),
    ("eval.n_worlds=100000", "eval.n_worlds=100000"),
    ("train.max_steps=0", "train.max_steps"),
    ("model=hf", "model.path"),
    ("model.attn_implementation=flash", "model.attn_implementation='flash'.*sdpa, eager"),
])
def test_bad_values_fail_before_any_work(override, message):
    cfg = _compose([override, "model.path=null"] if override == "model=hf" else [override])
    with pytest.raises(ConfigError, match=message):
        validate(cfg)


def test_compiling_on_a_cpu_without_a_cxx_compiler_is_refused_naming_the_way_out(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-c++-compiler")
    monkeypatch.setattr("pipeline.config._cuda_visible", lambda: False)
    with pytest.raises(ConfigError, match=r"train.torch_compile=regional.*'no-such-c\+\+-compiler'.*"
                                          r"train.torch_compile=none"):
        validate(_compose(["train.torch_compile=regional"]))
    monkeypatch.setattr("pipeline.config.PYTHON_H", Path("/no/such/include/Python.h"))
    with pytest.raises(ConfigError, match=r"compiler.*and the Python headers \(/no/such/include/Python.h"):
        validate(_compose(["train.torch_compile=full"]))
    assert validate(_compose(["train.torch_compile=none"])) == "marking-deadend"
    monkeypatch.setenv("CXX", "sh")  # any program on PATH, and headers that exist
    monkeypatch.setattr("pipeline.config.PYTHON_H", Path(__file__))
    assert validate(_compose(["train.torch_compile=full"])) == "marking-deadend"


@pytest.mark.parametrize("override", ["variant=bogus", "direction=up", "mode=sometimes", "data.frame=abc",
                                      "train.no_such_key=1", "train.torch_compile=true"])
def test_unknown_names_fail_at_compose_time(override):
    with pytest.raises(Exception) as info:
        _compose([override])
    text = str(info.value)
    assert override.split("=")[0].split(".")[-1] in text or "Could not find" in text


@pytest.mark.parametrize("sweep", sorted(p.stem for p in SWEEPS.glob("*.yaml")))
def test_sweep_files_compose_and_define_the_whole_grid(sweep):
    cfg = _compose(name=sweep, sweeps=True, hydra_node=True)
    params = cfg.hydra.sweeper.params
    assert params.direction == "fwd,bwd" and params.mode == "optimal,reachable"
    assert set(params.variant.split(",")) == set(MAP_VARIANTS) | {"none", "cot", "dfs"}
    assert cfg.skip_undefined is True


def test_paper_scale_presets_compose():
    cfg = _compose(["data=paper", "model=llama3_8b", "train=paper", "eval=paper"])
    assert cfg.model.dtype == "bfloat16" and cfg.model.max_length == 8192
    assert cfg.train.max_length == 8192 and cfg.train.warmup_ratio == 0.03 and cfg.train.weight_decay == 0.0
    assert cfg.eval.backend.value == "vllm"
    assert Path(cfg.data.test_file).name == "paper_test_3000.jsonl"


@pytest.mark.parametrize("launcher", ["local2", "slurm"])
def test_launcher_presets_compose(launcher):
    cfg = _compose([f"hydra/launcher={launcher}"], hydra_node=True)
    assert "_target_" in cfg.hydra.launcher


def test_train_config_schema_matches_train_settings():
    """The schema mirrors TrainSettings (kept apart so composing configs never imports torch)."""
    from dataclasses import fields

    from pipeline.config import TrainConfig
    from pipeline.finetune import TrainSettings
    from pipeline.finetune_step import _STEP_KEYS

    schema = {f.name for f in fields(TrainConfig)} - set(_STEP_KEYS)
    assert schema == {f.name for f in fields(TrainSettings)} - {"seed"}  # the job's seed seeds training
