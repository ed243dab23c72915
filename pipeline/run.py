"""`python -m pipeline.run`: the Hydra entry point. One job = data-build -> finetune -> eval (see
`pipeline.workflow.job`); with `-m`, Hydra sweeps the config groups into several jobs."""

import hydra
from omegaconf import DictConfig

from pipeline.workflow import job


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> float | None:
    return job.main(cfg)


if __name__ == "__main__":
    main()
