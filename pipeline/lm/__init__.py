"""Language-model code (torch and transformers, never Hydra or MLflow's run layout): chat encoding, the
word-level tokenizer, building or loading a model, training, and decoding."""
