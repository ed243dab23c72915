"""The training benchmark runs the default model yaml against its other newline cut (benchmarks/bench_train.py)."""

import re
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from pipeline.lm.training.compile import cpu_has_bf16

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_bench_train_runs_the_default_against_the_other_newline_cut(tmp_path):
    """The default model yaml (newlines composed) against `own`, each run built with its own cut, through the CPU
    default's train yaml (compiled layers), in two rounds (A B, then B A): every run prints its rates each round,
    and the ratio line gives each round's ratio. The bf16 peak is measured only where bf16 runs in hardware
    (emulated, it is no peak and takes about 18 s a measurement)."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_train.py"), "--only", "default", "--only", "other-newlines",
         "--conversations", "16", "--steps", "3", "--skip", "1", "--threads", "1",
         "--rounds", "2", "--model", str(ROOT / "conf" / "model" / "tiny.yaml")],
        capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "newlines composed)" in result.stdout
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


def test_bench_train_refuses_no_rounds(tmp_path):
    """``--rounds 0`` stops before any measurement, naming the value and what is allowed."""
    result = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_train.py"), "--rounds", "0"],
                            capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert result.returncode == 2
    assert "--rounds 0 must be at least 1" in result.stderr
    assert "matmul peak" not in result.stdout
