"""Every config group option, preset and sweep file composes; impossible combinations fail early."""

from pathlib import Path

import pytest
from hydra.core.config_store import ConfigStore
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Glob
from omegaconf import OmegaConf

from pipeline.workflow.config import ConfigError, UndefinedCell, register_configs, validate, variant_name
from pipeline.core.variants import ALIASES, PAPER_MAP_VARIANTS, PAPER_VARIANTS, SWITCHES, VARIANTS

from conftest import ROOT, compose_job
CONF, SWEEPS = ROOT / "conf", ROOT / "sweeps"
register_configs()


def _compose(overrides=(), name="config", sweeps=False, hydra_node=False):
    # As `--config-dir sweeps --config-name NAME`: the sweep file is primary, conf/ stays searchable.
    extra = [f"hydra.searchpath=[file://{CONF}]"] if sweeps else []
    return compose_job(None, *extra, *overrides, name=name, config_dir=SWEEPS if sweeps else CONF, toy=False,
                       return_hydra_config=hydra_node)


def _options(group: str) -> list[str]:
    """A group's options: its files under conf/, or the presets generated from the variants table."""
    files = [p.stem for p in (CONF / group).glob("*.yaml")]
    return sorted(files or [name.removesuffix(".yaml") for name in ConfigStore.instance().list(group)])


def _sweep_values(params, key: str) -> list[str]:
    """A sweep parameter's values, a glob over a group's options expanded as Hydra's sweeper does."""
    override = OverridesParser.create().parse_overrides([f"{key}={params[key]}"])[0]
    value = override.value()
    return value.filter(_options(key)) if isinstance(value, Glob) else list(override.sweep_string_iterator())


def test_default_job_is_bwd_marking_deadend_optimal():
    cfg = _compose()
    assert (cfg.direction.value, cfg.mode.value) == ("bwd", "optimal")
    assert validate(cfg).variant == "marking-deadend"


@pytest.mark.parametrize("group", ["direction", "mode", "baseline", "marking", "backtrack", "all_moves", "named",
                                   "variant", "model", "data", "train", "eval", "tracking"])
def test_every_group_option_composes(group):
    options = _options(group)
    assert options
    for option in options:
        cfg = _compose([f"{group}={option}", "model.path=x"] if option == "hf" else [f"{group}={option}"])
        if group in ("direction", "mode", "baseline"):
            assert cfg[group].value == option
        elif group in SWITCHES:
            assert cfg[group] is (option == "on")
        elif group == "variant":
            name = ALIASES.get(option, option)
            assert validate(_compose([f"variant={option}", f"mode={'reachable' if name == 'dfs' else 'optimal'}"])
                            ).variant == name
        else:
            OmegaConf.to_container(cfg, resolve=True, throw_on_missing=False)


def test_the_generated_groups_are_the_variants_table():
    assert _options("variant") == sorted([*VARIANTS, *ALIASES])
    for switch in SWITCHES:
        assert _options(switch) == ["off", "on"]
    assert not any((CONF / group).exists() for group in ("variant", "direction", "mode", "baseline", *SWITCHES))


@pytest.mark.parametrize("variant", list(PAPER_MAP_VARIANTS) + ["none", "cot"])
def test_variant_presets_name_their_row(variant):
    assert validate(_compose([f"variant={variant}"])).variant == variant


@pytest.mark.parametrize("variant", ["marking-deadend", "no-marking", "no-all-no-backtrack"])
def test_named_switch_names_the_expanded_states_of_any_map(variant):
    assert validate(_compose([f"variant={variant}", "named=on"])).variant == variant + "-named"
    assert validate(_compose([f"variant={variant}", "named=off"])).variant == variant


@pytest.mark.parametrize("baseline", ["none", "cot", "dfs"])
def test_named_without_a_map_is_refused(baseline):
    with pytest.raises(ConfigError, match=f"named=on .* baseline={baseline} has none. Allowed: named=off"):
        validate(_compose([f"variant={baseline}", "named=on", "mode=reachable"]))


def test_models_trained_from_scratch_drop_the_instruction_and_pretrained_ones_keep_it():
    assert _compose().model.prompt == "task" and _compose(["model=toy"]).model.prompt == "task"
    assert _compose(["model=llama3_8b"]).model.prompt == "paper"
    assert _compose(["model=hf", "model.path=x"]).model.prompt == "paper"
    assert _compose().model.log_model == "transformers"
    assert _compose(["model=llama3_8b"]).model.log_model == "reference"


def test_the_cpu_default_anchors_its_plan_and_the_paper_presets_keep_the_papers():
    assert _compose().model.plan_form == "anchored" and _compose().train.position_stretch == 2
    for preset in (["model=toy"], ["model=llama3_8b"], ["model=hf", "model.path=x"]):
        assert _compose(preset).model.plan_form == "moves", preset
    assert _compose(["train=paper"]).train.position_stretch == 1


def test_the_cpu_default_computes_attention_as_matmuls_and_the_paper_model_keeps_sdpa():
    assert _compose().model.attn_implementation == "eager" and _compose(["model=toy"]).model.attn_implementation == "sdpa"
    assert _compose(["model=llama3_8b"]).model.attn_implementation == "sdpa"


def test_aliases_and_command_line_switches_win_over_presets():
    assert validate(_compose(["variant=marking"])).variant == "marking-deadend"
    assert validate(_compose(["variant=nomarking"])).variant == "no-marking"
    assert validate(_compose(["variant=no-marking", "marking=on"])).variant == "marking-deadend"
    assert validate(_compose(["variant=marking-deadend", "backtrack=off"])).variant == "no-backtrack"


def test_dfs_preset_is_reachable_and_optimal_dfs_is_refused():
    assert validate(_compose(["variant=dfs"])).variant == "dfs"
    with pytest.raises(UndefinedCell, match="mode=reachable"):
        validate(_compose(["variant=dfs", "mode=optimal"]))


def test_marking_without_all_moves_is_refused_naming_the_values():
    with pytest.raises(ConfigError, match="all_moves=False, marking=True"):
        variant_name(_compose(["variant=no-all", "marking=on"]))


@pytest.mark.parametrize("override, message", [
    ("data.train_size_x=[1,5]", "data.train_size_x"),
    ("data.test_size_y=[2,30]", r"data.test_size_y=\[2, 30\] is not allowed; expected 2 <= min <= max <= frame \(6\)"),
    ("data.p_pit=[0.5,1.5]", "data.p_pit"),
    ("data.train_deep=1.5", r"data.train_deep=1.5 is not allowed; expected a fraction in \[0, 1\]"),
    ("data.generator=paper data.train_deep=0.5",
     r"data.train_deep=0.5 is not allowed; expected 0 with generator=paper"),
    ("data.n_train=0", "data.n_train"),
    ("eval.n_worlds=100000", "eval.n_worlds=100000"),
    ("train.max_steps=0", "train.max_steps"),
    ("model=hf", "model.path"),
    ("model.attn_implementation=flash", "model.attn_implementation='flash'.*sdpa, eager"),
    ("model.prompt=short", "model.prompt='short' is not allowed; expected one of paper, task, cells, axes"),
    ("model.log_model=copy", "model.log_model='copy' is not allowed; expected one of transformers, reference"),
    ("model.numbers=roman", "model.numbers='roman' is not allowed; expected one of whole, digits"),
    ("model=hf model.path=x model.numbers=digits", "model.numbers='digits' is not allowed; expected whole for a pretrained"),
    ("model.newlines=crlf", "model.newlines='crlf' is not allowed; expected one of own, joined"),
    ("model=hf model.path=x model.newlines=joined", "model.newlines='joined' is not allowed; expected own for a pretrained"),
    ("model.spaces=composed", "model.spaces='composed' is not allowed; expected one of own, joined, phrases"),
    ("model=hf model.path=x model.spaces=joined", "model.spaces='joined' is not allowed; expected own for a pretrained"),
    ("eval.rules=strict", "eval.rules='strict' is not allowed; expected one of project, paper"),
    ("train.long_conversations=cut", "train.long_conversations='cut' is not allowed; expected one of drop, truncate"),
    ("train.position_stretch=0.5", "train.position_stretch=0.5 is not allowed; expected a number >= 1"),
    ("eval.curve_valid=true", "eval.curve_valid=True is not allowed; expected false, or true with curve=true and n_valid >= 1"),
])
def test_bad_values_fail_before_any_work(override, message):
    cfg = _compose([override, "model.path=null"] if override == "model=hf" else override.split())
    with pytest.raises(ConfigError, match=message):
        validate(cfg)


def test_compiling_on_a_cpu_without_a_cxx_compiler_is_refused_naming_the_way_out(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-c++-compiler")
    monkeypatch.setattr("pipeline.workflow.config._cuda_visible", lambda: False)
    with pytest.raises(ConfigError, match=r"train.torch_compile=regional.*'no-such-c\+\+-compiler'.*"
                                          r"train.torch_compile=none"):
        validate(_compose(["train.torch_compile=regional"]))
    monkeypatch.setattr("pipeline.workflow.config.PYTHON_H", Path("/no/such/include/Python.h"))
    with pytest.raises(ConfigError, match=r"compiler.*and the Python headers \(/no/such/include/Python.h"):
        validate(_compose(["train.torch_compile=full"]))
    assert validate(_compose(["train.torch_compile=none"])).variant == "marking-deadend"
    monkeypatch.setenv("CXX", "sh")  # any program on PATH, and headers that exist
    monkeypatch.setattr("pipeline.workflow.config.PYTHON_H", Path(__file__))
    assert validate(_compose(["train.torch_compile=full"])).variant == "marking-deadend"


@pytest.mark.parametrize("override", ["variant=bogus", "direction=up", "mode=sometimes", "data.frame=abc",
                                      "train.no_such_key=1", "train.torch_compile=true"])
def test_unknown_names_fail_at_compose_time(override):
    with pytest.raises(Exception) as info:
        _compose([override])
    text = str(info.value)
    assert override.split("=")[0].split(".")[-1] in text or "Could not find" in text


@pytest.mark.parametrize("sweep", ["paper", "smoke"])
def test_sweep_files_compose_and_define_the_whole_grid(sweep):
    cfg = _compose(name=sweep, sweeps=True, hydra_node=True)
    params = cfg.hydra.sweeper.params
    assert params.direction == "fwd,bwd" and params.mode == "optimal,reachable"
    assert sorted(_sweep_values(params, "variant")) == sorted(PAPER_VARIANTS)
    assert cfg.skip_undefined is True
    if sweep == "smoke":  # two toy jobs at a time, on one thread each
        assert cfg.hydra.launcher.n_jobs == 2 and cfg.threads == 1


def test_every_sweep_file_is_tested():
    assert sorted(p.stem for p in SWEEPS.glob("*.yaml")) == ["cpu_paper", "cpu_study", "extrapolation", "paper", "smoke"]


def test_the_extrapolation_study_runs_each_lever_alone_with_two_seeds_on_the_default_job():
    cfg = _compose(name="extrapolation", sweeps=True, hydra_node=True)
    params = cfg.hydra.sweeper.params
    assert cfg.hydra.launcher.n_jobs == 2 and cfg.threads == 1 and params.seed == "0,1"
    levers = params["+lever"].split(",")
    assert sorted(levers) == sorted(p.stem for p in (SWEEPS / "lever").glob("*.yaml"))
    def flat(job) -> dict:
        """The job's data, model and train settings and its named switch, as dotted keys."""
        tree = OmegaConf.to_container(job, resolve=False)
        return {"named": tree["named"], **{f"{section}.{key}": value for section in ("data", "model", "train")
                                            for key, value in tree[section].items()}}

    default = flat(_compose(["+lever=default"], name="extrapolation", sweeps=True))
    changed = {}
    for lever in levers:
        job = _compose([f"+lever={lever}"], name="extrapolation", sweeps=True)
        assert validate(job).variant in ("marking-deadend", "marking-deadend-named") and job.train.bf16 is False
        assert job.eval.n_valid == 200 and job.train.max_steps == 5000 and job.threads == 1
        changed[lever] = sorted(key for key, value in flat(job).items() if value != default[key])
    assert changed == {"default": [], "named": ["named"], "plain": ["model.step_headers"],
                       "cells": ["model.prompt"], "corner": ["data.train_deep"], "alternate": ["model.positions"],
                       "distractors": ["data.train_distractors"], "adamw": ["train.optimizer"],
                       "whole": ["model.numbers"],
                       "log_length": ["model.attention_scale", "model.attn_implementation"],
                       "linear_cells": ["model.coordinate_init"], "weight_decay": ["train.weight_decay"],
                       "wide_mlp": ["model.intermediate_size"], "edge_labels": ["data.mask_edge_labels"],
                       "axes": ["model.prompt"], "plain_positions": ["train.position_stretch"],
                       "moves_plan": ["model.plan_form"], "joined": ["model.newlines"], "own": ["model.newlines"],
                       "own_spaces": ["model.spaces"], "joined_spaces": ["model.spaces"]}


def test_cpu_study_is_the_optimal_half_of_table_1_with_two_seeds_where_asked():
    cfg = _compose(name="cpu_study", sweeps=True, hydra_node=True)
    assert cfg.hydra.launcher._target_.endswith("JoblibLauncher") and cfg.hydra.launcher.n_jobs == 2
    cells = cfg.hydra.sweeper.params["+study_cell"].split(",")
    jobs = []
    for cell in cells:
        job = _compose([f"+study_cell={cell}"], name="cpu_study", sweeps=True)
        assert job.mode.value == "optimal" and job.threads == 1 and job.eval.curve and job.train.log_checkpoints
        assert OmegaConf.masked_copy(job, ["data", "model"]) == OmegaConf.masked_copy(_compose(), ["data", "model"])
        jobs.append((validate(job).variant, job.direction.value if validate(job).variant != "none" else "-", job.seed))
    assert sorted(jobs) == sorted([
        ("none", "-", 0), ("none", "-", 1), ("cot", "fwd", 0), ("cot", "bwd", 0),
        ("marking-deadend", "fwd", 0), ("marking-deadend", "bwd", 0), ("marking-deadend", "bwd", 1),
        ("no-marking", "fwd", 0), ("no-marking", "bwd", 0), ("marking-deadend-named", "bwd", 0)])


def test_cpu_paper_is_every_cell_of_tables_1_3_7_8_with_table_1s_bwd_cells_twice():
    from pipeline.core.variants import PAPER_MAP_VARIANTS
    from pipeline.workflow.config import UndefinedCell
    from pipeline.workflow.job import job_texts, step_hashes

    cfg = _compose(name="cpu_paper", sweeps=True, hydra_node=True)
    assert cfg.hydra.launcher.n_jobs == 2 and cfg.threads == 1 and cfg.skip_undefined
    params = cfg.hydra.sweeper.params
    jobs, finetunes, skipped = {}, set(), []
    for mode in _sweep_values(params, "mode"):
        for cell in _sweep_values(params, "+study_cell"):
            job = _compose([f"mode={mode}", f"+study_cell={cell}"], name="cpu_paper", sweeps=True)
            try:
                settings = validate(job)
            except UndefinedCell:
                skipped.append((cell, mode))
                continue
            direction = "-" if settings.variant in ("none", "dfs") else job.direction.value
            key = (settings.variant, direction, mode, job.seed)
            assert key not in jobs, key
            jobs[key] = job
            finetunes.add(step_hashes(settings, job.seed, job_texts(job, settings))["finetune"])
            # The CPU default's recipe; only Figure 3's cells log and evaluate their checkpoints.
            assert OmegaConf.masked_copy(job, ["data", "model"]) == OmegaConf.masked_copy(_compose(), ["data", "model"])
            figure3 = settings.variant in ("none", "cot", "marking-deadend") and direction in ("-", "bwd")
            assert job.eval.curve == job.train.log_checkpoints == figure3, key
    assert skipped == [("dfs", "optimal")]
    table1_bwd = [("none", "-"), ("cot", "bwd"), ("marking-deadend", "bwd"), ("no-marking", "bwd")]
    expected = {(variant, direction, mode, 0) for mode in ("optimal", "reachable")
                for variant in (*PAPER_MAP_VARIANTS, "cot") for direction in ("fwd", "bwd")}
    expected |= {("none", "-", mode, 0) for mode in ("optimal", "reachable")} | {("dfs", "-", "reachable", 0)}
    expected |= {(variant, direction, mode, 1)
                 for variant, direction in table1_bwd for mode in ("optimal", "reachable")}
    assert set(jobs) == expected and len(jobs) == 39
    assert len(finetunes) == 39   # every job trains a model of its own


def test_paper_scale_presets_compose():
    cfg = _compose(["data=paper", "model=llama3_8b", "train=paper", "eval=paper"])
    assert cfg.model.dtype == "bfloat16" and cfg.model.max_length == 8192
    assert cfg.train.warmup_ratio == 0.03 and cfg.train.weight_decay == 0.0 and cfg.train.learning_rate == 2e-5
    assert cfg.eval.backend == "vllm"
    assert cfg.data.test_file == "paper"   # resolved to the fetched, checksummed file (pipeline.workflow.paper_data)
    # The paper's code truncates a conversation longer than the context; the CPU default drops it.
    assert cfg.train.long_conversations == "truncate" and _compose().train.long_conversations == "drop"


def test_settings_added_since_keep_the_step_hashes_of_finished_runs(monkeypatch):
    # Settings added since (train.long_conversations, model.step_headers/positions/rope_theta/numbers, the texts'
    # step_headers, eval.n_valid, data.train_deep) count in a hash only when set, so a store's finished CPU-default and toy steps
    # stay reusable: these are the hashes of the code before them (commit d5259f8). The CPU default's eval
    # scores validation worlds now (eval.n_valid=200), a new output: its eval hash is new. Change these only for
    # a change meant to rerun finished steps (README, "Step versions").
    from pipeline.workflow import job as job_module
    from pipeline.workflow.job import job_texts, step_hashes

    # finetune 3 (length-grouped batches no longer cut across two length groups) reran every finetune and eval:
    # the settings' invariants below are pinned under finetune 2, and version 3 gives new hashes.
    current = job_module.STEP_VERSIONS["finetune"]
    assert current == 3

    def hashes(*overrides, toy, version=2):
        monkeypatch.setitem(job_module.STEP_VERSIONS, "finetune", version)
        cfg = compose_job(None, "tracking.root=x", *overrides, toy=toy)
        job = validate(cfg)
        return step_hashes(job, cfg.seed, job_texts(cfg, job))

    old_default = ("data.train_deep=0", "train.optimizer=adamw", "train.bf16_when_faster=false", "model.numbers=whole",
                   "model.attn_implementation=sdpa", "train.position_stretch=1", "model.plan_form=moves",
                   "model.newlines=own", "train.batch_threads=1", "train.labelled_logits=false",
                   "train.muon_bf16=false", "model.spaces=own")
    assert hashes("eval.n_valid=0", *old_default, toy=False) == {
        "data-build": "9084abe767f5f3cf", "finetune": "9f74feb50b9e71d8", "eval": "7a5f1b9983e9f635"}
    assert hashes(*old_default, toy=False)["eval"] != "7a5f1b9983e9f635"
    # The CPU default's recipe since (Muon, half the train worlds deep, bf16 only where faster, numbers as
    # digits): new steps.
    new = hashes(toy=False)
    assert new["data-build"] != "9084abe767f5f3cf" and new["finetune"] != "9f74feb50b9e71d8"
    assert hashes(toy=True) == {"data-build": "128801358476e7a8", "finetune": "2404019bf8a1b813",
                                "eval": "4141ac65b7504e8f"}
    now = hashes(toy=True, version=current)
    assert now["data-build"] == "128801358476e7a8" and now["finetune"] != "2404019bf8a1b813"
    assert now["eval"] != "4141ac65b7504e8f"
    for override in ("model.step_headers=plain", "model.positions=nope", "model.rope_theta=100",
                     "model.numbers=digits"):
        assert hashes(override, toy=True)["finetune"] != "2404019bf8a1b813", override
    for override in ("model.step_headers=plain", "model.numbers=digits", "model.plan_form=anchored"):
        assert hashes(override, toy=True)["data-build"] != "128801358476e7a8", override
    assert hashes("train.long_conversations=truncate", toy=True)["finetune"] != "2404019bf8a1b813"
    assert hashes("data.train_deep=0.5", toy=True)["data-build"] != "128801358476e7a8"
    assert hashes("data.train_distractors=8", toy=True)["data-build"] != "128801358476e7a8"
    assert hashes("data.mask_edge_labels=true", toy=True)["data-build"] != "128801358476e7a8"
    assert hashes("train.optimizer=muon", toy=True)["finetune"] != "2404019bf8a1b813"
    assert hashes("train.muon_bf16=false", toy=False)["finetune"] != new["finetune"]
    # Stretched positions (the CPU default since) train other numbers: a new step; plain positions' runs stay reusable.
    assert hashes("train.position_stretch=1", toy=False)["finetune"] != new["finetune"]
    assert hashes("train.position_stretch=1", toy=False)["data-build"] == new["data-build"]
    # The anchored Plan (the CPU default since) writes other texts: a new data-build; the paper's Plan's runs stay reusable.
    assert hashes("model.plan_form=moves", toy=False)["data-build"] != new["data-build"]
    assert hashes("model.plan_form=moves", toy=False)["finetune"] != new["finetune"]
    # Eager attention (the CPU default since) trains other numbers than sdpa: a new step; sdpa's runs stay reusable.
    assert hashes("model.attn_implementation=sdpa", toy=False)["finetune"] != new["finetune"]
    assert hashes("model.attn_implementation=sdpa", toy=False)["data-build"] == new["data-build"]
    # Newlines composed (the CPU default since) cut other tokens: a new data-build (its token counts) and finetune;
    # the earlier default's (`own`) runs stay reusable.
    assert hashes("model.newlines=own", toy=False)["data-build"] != new["data-build"]
    assert hashes("model.newlines=own", toy=False)["finetune"] != new["finetune"]
    # The last layer cut to the trained positions (the CPU default since) rounds otherwise: a new finetune; the runs
    # before it stay reusable, and without labelled_logits the switch is off and counts nothing.
    assert hashes("train.labelled_last_layer=false", toy=False)["finetune"] != new["finetune"]
    assert hashes("train.labelled_last_layer=false", toy=False)["data-build"] == new["data-build"]
    assert (hashes("train.labelled_logits=false", toy=False)
            == hashes("train.labelled_logits=false", "train.labelled_last_layer=false", toy=False))
    # Spaces joined (the CPU default then) cut other tokens: a new data-build (its token counts) and finetune; the
    # earlier default's (`own`) runs stay reusable.
    joined, own = hashes("model.spaces=joined", toy=False), hashes("model.spaces=own", toy=False)
    assert joined["data-build"] != own["data-build"] and joined["finetune"] != own["finetune"]
    # Phrases (the CPU default since) cut other tokens again: new steps; spaces joined's runs stay reusable.
    phrases = hashes("model.spaces=phrases", toy=False)
    assert phrases == new and phrases["data-build"] != joined["data-build"] and phrases["finetune"] != joined["finetune"]


@pytest.mark.parametrize("launcher", ["local2", "slurm", "local_submitit"])
def test_launcher_presets_compose(launcher):
    cfg = _compose([f"hydra/launcher={launcher}"], hydra_node=True)
    assert "_target_" in cfg.hydra.launcher


def test_test_worlds_outside_a_scratch_models_coordinates_are_refused_naming_a_cell(paper_test_file):
    # The paper's worlds reach (19, y) in a 20 x 20 frame; a CPU-default model knows cells 0..5 (frame 6).
    cfg = _compose([f"data.test_file={paper_test_file}", "data.n_test=50"])
    with pytest.raises(ConfigError, match=r"test world \d+ has the cell \(\d+, \d+\) outside .*data.frame=6.*"
                                          r"allowed: data.frame >= \d+"):
        validate(cfg)
    assert validate(_compose([f"data.test_file={paper_test_file}", "data.n_test=50", "data.frame=20"]))


def test_a_test_file_with_too_few_or_malformed_worlds_is_refused(tmp_path, paper_test_file):
    short = tmp_path / "short.jsonl"
    short.write_text("".join(paper_test_file.read_text().splitlines(keepends=True)[:3]))
    with pytest.raises(ConfigError, match=r"data.n_test=10 but data.test_file=.* holds 3 worlds; allowed: 1..3"):
        validate(_compose([f"data.test_file={short}", "data.n_test=10", "data.frame=20"]))
    broken = tmp_path / "broken.jsonl"
    broken.write_text("{not json\n")
    with pytest.raises(ConfigError, match=r"data.test_file=.*broken.jsonl.*:1:"):
        validate(_compose([f"data.test_file={broken}", "data.n_test=1", "data.frame=20"]))
