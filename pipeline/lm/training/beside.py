"""The process that compiles a job's decoder layer beside its data-build, seen from the job's side: started with
the command line (`start_early`) or when the job asks (`start`), handed the job's settings or ended (`send`). What
the process runs is `pipeline.lm.training.precompile`; `pipeline.lm.training.compile.compile_beside` decides.
Nothing here imports torch: the command line starts the process before its own imports."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Sequence

# Command-line flags with which `python -m pipeline.run` runs no job: no process is started for them.
_NO_JOB_FLAGS = {"--help", "-h", "--hydra-help", "--info", "-i", "--cfg", "-c", "--shell-completion", "-sc",
                 "--version"}
# How long the process waits for its settings: a job sends them seconds after its command line starts; a sweep
# whose jobs run in processes of their own (hydra/launcher=local2, SLURM) sends none, and the process ends.
SETTINGS_TIMEOUT = 120
# The process `start_early` started, and the file its output goes to, until `take` hands them on.
_early: tuple[subprocess.Popen, Path] | None = None


def start() -> tuple[subprocess.Popen, Path]:
    """The process, started: it imports, then waits for its settings on its standard input."""
    output = Path(tempfile.mkdtemp(prefix="cogmap-precompile-")) / "output.txt"
    with output.open("wb") as sink:
        process = subprocess.Popen([sys.executable, "-m", "pipeline.lm.training.precompile", str(output.parent)],
                                   stdin=subprocess.PIPE, stdout=sink, stderr=subprocess.STDOUT)
    return process, output


def start_early(argv: Sequence[str]) -> None:
    """`start` the process at the command line's start, unless ``argv`` asks for no job (help, config)."""
    global _early
    if _early is None and not set(argv) & _NO_JOB_FLAGS:
        _early = start()


def take() -> tuple[subprocess.Popen, Path] | None:
    """The process `start_early` started, if it still waits (once: a later caller gets None)."""
    global _early
    early, _early = _early, None
    return early if early is not None and early[0].poll() is None else None


def end_early() -> None:
    """End the process `start_early` started, if it waits (a job that compiles nothing here)."""
    early = take()
    if early is not None:
        send(early[0], None)


def send(process: subprocess.Popen, settings: dict | None) -> None:
    """Hand the process its settings; None ends it (its folder removed)."""
    try:
        if settings is not None:
            process.stdin.write((json.dumps(settings) + "\n").encode())
        process.stdin.close()
    except (BrokenPipeError, OSError):  # it ended already: the job compiles for itself
        pass
