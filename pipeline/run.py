"""`python -m pipeline.run`: the Hydra entry point. One job = data-build -> finetune -> eval (see
`pipeline.workflow.job`); with `-m`, Hydra sweeps the config groups into several jobs."""

import sys

if __name__ == "__main__":
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
