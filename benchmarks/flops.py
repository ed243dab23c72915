"""FLOP counts for the benchmarks: useful forward+backward FLOPs of training a causal LM."""

from __future__ import annotations

from typing import Iterable

import torch
from transformers import PreTrainedModel


def count_parameters(model: torch.nn.Module) -> int:
    """Number of distinct parameters (a tied embedding counts once)."""
    return sum(p.numel() for p in model.parameters())


def matmul_parameters(model: PreTrainedModel) -> int:
    """Parameters that take part in a matmul per token: all but an untied input embedding (a lookup)."""
    n = count_parameters(model)
    if not model.config.tie_word_embeddings:
        n -= model.get_input_embeddings().weight.numel()
    return n


def training_flops_per_token(model: PreTrainedModel, context: float) -> float:
    """Forward+backward FLOPs per token: ``6 N`` for the weights plus ``12 * layers * hidden * context`` for
    attention (QK^T and AV, 2 FLOPs per multiply-add, backward twice forward), where ``context`` is the mean
    number of keys a query attends to ((L+1)/2 for a causal sequence of length L)."""
    config = model.config
    attention = 12 * config.num_hidden_layers * config.hidden_size * context
    return 6 * matmul_parameters(model) + attention


def training_flops(model: PreTrainedModel, lengths: Iterable[int]) -> float:
    """Useful forward+backward FLOPs of training on causal sequences of these lengths (padding excluded)."""
    return sum(length * training_flops_per_token(model, (length + 1) / 2) for length in lengths)
