"""What a fine-tuning run produces, and where in its output folder (light: no torch, so the workflow can read
a run's result and checkpoints without importing the trainer)."""

from __future__ import annotations

from dataclasses import dataclass, field

CHECKPOINTS_DIR, MODEL_DIR, RESULT_FILE = "checkpoints", "model", "train_result.json"


@dataclass
class TrainResult:
    """What a fine-tuning run produced and how fast."""

    final_loss: float | None          # the last logged training loss
    mean_loss: float                  # mean training loss of this session (transformers' train_loss)
    token_accuracy: float | None      # argmax accuracy on held-out gpt tokens (None: no eval split)
    tokens_trained: int               # real (non-padding) tokens over the whole run, resumed part included
    real_token_fraction: float        # real tokens / tokens computed, over the whole run
    tokens_per_second: float          # real tokens per second of this session
    train_seconds: float              # wall time of this session's training loop
    global_step: int
    model_dir: str
    checkpoint_steps: list[int] = field(default_factory=list)
    dropped: int = 0                  # conversations over max_length not trained on (dropped, or no target left)
    truncated: int = 0                # conversations over max_length trained on their first max_length tokens
    resumed_from: str | None = None
    parameters: int = 0               # the model's parameters (a tied embedding counted once)
