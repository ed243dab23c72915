"""`python -m pipeline.run`: the Hydra entry point. One job = data-build -> finetune -> eval (see
`pipeline.workflow.job`); with `-m`, Hydra sweeps the config groups into several jobs."""

import atexit
import os
import sys

_ended_well = False  # set once the command's work ended normally (its exit status 0)


def _exit_at_once() -> None:
    """The last of the exit handlers (registered first): after a normal end, once the others have run, the process
    ends without the interpreter's teardown, which freed a job's objects one by one for about 2 s (README, Speed).
    Any other end keeps Python's own exit and its status."""
    if _ended_well:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):  # a closed pipe or stream: nothing left to write to it
                pass
        os._exit(0)


if __name__ == "__main__":
    atexit.register(_exit_at_once)
    # Before this process's own imports: the process that compiles the job's layers beside its data-build imports
    # meanwhile (pipeline/lm/training/precompile.py; it ends at once where the job compiles nothing).
    from pipeline.lm.training.beside import start_early

    start_early(sys.argv[1:])

import hydra  # noqa: E402 - after the early start above
from omegaconf import DictConfig  # noqa: E402

from pipeline.workflow import job  # noqa: E402


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    return job.main(cfg)


if __name__ == "__main__":
    main()
    _ended_well = True
