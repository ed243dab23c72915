"""The training benchmark runs the default model yaml against its other newline cut (benchmarks/bench_train.py)."""

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from omegaconf import OmegaConf

from pipeline.lm.training.compile import cpu_has_bf16

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_bench_train_runs_the_default_against_the_other_newline_cut(tmp_path):
    """The default model yaml (newlines composed, spaces phrases) against `own`, each run built with its own cut,
    through the CPU default's train yaml (compiled layers), in two rounds (A B, then B A): every run prints its
    rates each round, and the ratio line gives each round's ratio. The bf16 peak is measured only where bf16 runs
    in hardware (emulated, it is no peak and takes about 18 s a measurement)."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_train.py"), "--only", "default", "--only", "other-newlines",
         "--conversations", "16", "--steps", "3", "--skip", "1", "--threads", "1",
         "--rounds", "2", "--model", str(ROOT / "conf" / "model" / "tiny.yaml")],
        capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "newlines composed, spaces phrases)" in result.stdout
    lines = result.stdout.splitlines()
    runs = [line.split(": ")[0] for line in lines if "real tokens/s over all steps" in line]
    default = next(run for run in runs if "newlines" not in run).removesuffix(" (round 1)")
    other = f"{default}, newlines own"
    assert runs == [f"{default} (round 1)", f"{other} (round 1)", f"{other} (round 2)", f"{default} (round 2)"]
    ratio = [line for line in lines if line.startswith(f"{other} / {default} tokens/s")]
    assert len(ratio) == 1 and re.search(r"in steady state \(rounds: [\d.]+x, [\d.]+x\)", ratio[0]), ratio
    bf16_peak = torch.cuda.is_available() or cpu_has_bf16()  # a GPU measures bf16 whatever its host CPU
    assert ("bf16 not measured" in result.stdout) == (not bf16_peak)
    assert ("% of the bf16 peak" in result.stdout) == bf16_peak


def test_switcher_flips_the_trainers_setting_in_turns_of_every_steps():
    """`Switcher` takes the default's value for ``every`` steps, then the other run's, and so on, on the object
    bound to it, and records which value each step ran with; unbound, it stops at the first step."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from transformers import TrainerControl, TrainerState

    from bench_train import Switcher

    class Trainer:  # what finetune binds: the setting lives on the trainer
        labelled_last_layer = True

    switcher, trainer, state = Switcher("whole-last-layer", 2), Trainer(), TrainerState()
    args, control = None, TrainerControl()  # the arguments are not read
    with pytest.raises(RuntimeError, match="no trainer bound"):
        switcher.on_step_begin(args, state, control)
    switcher.bind(trainer)
    seen = []
    for step in range(7):
        state.global_step = step
        switcher.on_step_begin(args, state, control)
        seen.append(trainer.labelled_last_layer)
        state.num_input_tokens_seen += 10
        switcher.on_step_end(args, state, control)
    assert seen == [True, True, False, False, True, True, False]
    assert switcher.switched == [not value for value in seen]
    assert [n for _, n in switcher.steps] == [10] * 7
    assert switcher.steady_of(0, True)[2] == 3 and switcher.steady_of(2, False, range(2, 6))[2] == 2


def _bench_main(monkeypatch, flags):
    """`bench_train.main` run in this process with ``flags``: no interpreter and imports to start."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_train

    monkeypatch.setattr(sys, "argv", ["bench_train.py", *flags])
    threads = torch.get_num_threads()
    try:
        bench_train.main()
    finally:  # it sets this process's threads to its --threads
        torch.set_num_threads(threads)


@pytest.mark.slow
def test_bench_train_switches_the_last_layer_within_one_run(tmp_path, monkeypatch, capsys):
    """``--switch whole-last-layer``: one run of the default (through finetune, which binds the trainer: unbound,
    the switcher stops) that computes the whole last layer every other 2 steps; each setting's steady steps
    counted apart, their ratio over the steady state and each half of it, and the shares of the peak. The CPU
    default's train yaml without compiling, so the run takes seconds."""
    train = tmp_path / "train.yaml"
    OmegaConf.save(OmegaConf.merge(OmegaConf.load(ROOT / "conf" / "train" / "cpu.yaml"), {"torch_compile": "none"}),
                   train)
    _bench_main(monkeypatch, ["--switch", "whole-last-layer", "--conversations", "16", "--steps", "12", "--skip", "4",
                              "--every", "2", "--threads", "1", "--train", str(train)])
    lines = capsys.readouterr().out.splitlines()
    assert sum("real tokens/s over all steps" in line for line in lines) == 1
    steady = [line for line in lines if "(medians of its 4 steps after step 4)" in line]
    assert len(steady) == 2 and ", whole last layer:" in steady[1], steady
    ratio = [line for line in lines if "switched within one run:" in line]
    assert len(ratio) == 1 and re.search(r"[\d.]+x \(halves of the steady state: [\d.]+x, [\d.]+x\)", ratio[0])
    assert sum("steady state" in line and "% of the fp32 peak" in line for line in lines) == 2


@pytest.mark.parametrize("flags, message", [
    (["--rounds", "0"], "--rounds 0 must be at least 1"),
    (["--switch", "all-logits", "--only", "default"], "--switch all-logits is one run of its own"),
    (["--switch", "all-logits", "--every", "5", "--skip", "9"], "got --every 5, --skip 9, --steps 60"),
    (["--switch", "all-logits", "--train", str(ROOT / "conf" / "train" / "toy.yaml")],
     "--switch all-logits: the train yaml computes the logits everywhere already"),
])
def test_bench_train_refuses_what_it_cannot_measure(monkeypatch, capsys, flags, message):
    """No rounds, a switch with other runs, too few steps for each setting in each half of the steady state, or a
    switch the train yaml has no other value for: each stops before any measurement, naming what is wrong."""
    with pytest.raises(SystemExit) as stopped:
        _bench_main(monkeypatch, flags)
    assert stopped.value.code == 2
    out, err = capsys.readouterr()
    assert message in err and "matmul peak" not in out
