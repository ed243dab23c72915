"""The workflow (Hydra and MLflow): the structured config and its checks, the store and step reuse, one
module per step (data-build, finetune, eval) and the job that chains them."""
