"""The training benchmark runs the default model yaml against its other newline cut (benchmarks/bench_train.py)."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_bench_train_runs_the_default_against_the_other_newline_cut(tmp_path):
    """The default model yaml (newlines composed) against `own`, each run built with its own cut, through the CPU
    default's train yaml (compiled layers): both print their rates and the ratio line."""
    result = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "bench_train.py"), "--only", "default", "--only", "other-newlines",
         "--conversations", "16", "--steps", "3", "--skip", "1", "--threads", "1",
         "--model", str(ROOT / "conf" / "model" / "tiny.yaml")],
        capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "newlines composed)" in result.stdout
    assert "newlines own: " in result.stdout and "newlines own / default" in result.stdout
