"""The training benchmark runs the default model yaml against its other newline cut (benchmarks/bench_train.py)."""

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
    default's train yaml (compiled layers): both print their rates and the ratio line. The bf16 peak is measured
    only where bf16 runs in hardware (emulated, it is no peak and takes about 18 s a measurement)."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_train.py"), "--only", "default", "--only", "other-newlines",
         "--conversations", "16", "--steps", "3", "--skip", "1", "--threads", "1",
         "--model", str(ROOT / "conf" / "model" / "tiny.yaml")],
        capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "newlines composed)" in result.stdout
    assert "newlines own: " in result.stdout and "newlines own / default" in result.stdout
    bf16_peak = torch.cuda.is_available() or cpu_has_bf16()  # a GPU measures bf16 whatever its host CPU
    assert ("bf16 not measured" in result.stdout) == (not bf16_peak)
    assert ("% of the bf16 peak" in result.stdout) == bf16_peak
