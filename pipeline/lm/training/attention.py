"""Causal attention in two halves of its queries, for training (`TrainSettings.attention_halves`).

Eager attention computes every query's scores against every key and masks the future away: half of a causal
sequence's scores are computed only to be zeroed. Cut the queries in two: the first half can see only the first
half of the keys, so its scores, softmax and weighted values are computed against those alone, and the second half
against all of them. A quarter of the scores is never computed: the same attention (a masked score's weight is
exactly zero after the softmax, in fp32), summed in other blocks. Only where a training forward has as many queries
as keys (no KV cache) and no attention dropout; otherwise, and in decoding, it is the model's eager attention.
"""

from __future__ import annotations

import logging
from contextlib import contextmanager

import torch
from torch import nn
from transformers import AttentionInterface, PreTrainedModel
from transformers.masking_utils import AttentionMaskInterface, eager_mask
from transformers.models.llama.modeling_llama import eager_attention_forward, repeat_kv

log = logging.getLogger(__name__)

HALVES = "eager_causal_halves"  # its name in transformers' attention registry, while a model trains with it
# Models whose eager attention is transformers' generic one (scores, additive mask, fp32 softmax, weighted values),
# which `causal_halves_attention` computes in pieces; another keeps its own, with a warning.
GENERIC_EAGER_MODELS = ("LlamaForCausalLM", "SmolLM3ForCausalLM")


def causal_halves_attention(module: nn.Module, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor,
                            attention_mask: torch.Tensor | None, scaling: float, dropout: float = 0.0, **kwargs):
    """Eager attention (transformers' `eager_attention_forward`) with the queries cut in two halves, the first
    against the first half of the keys only (see the module docstring). Returns the output and no weights."""
    length = query.shape[2]
    if key.shape[2] != length or length < 2 or (dropout and module.training):
        return eager_attention_forward(module, query, key, value, attention_mask, scaling, dropout, **kwargs)
    key = repeat_kv(key, module.num_key_value_groups)
    value = repeat_kv(value, module.num_key_value_groups)
    half = length // 2
    outputs = []
    for start, end in ((0, half), (half, length)):
        weights = torch.matmul(query[:, :, start:end], key[:, :, :end].transpose(2, 3)) * scaling
        if attention_mask is not None:
            weights = weights + attention_mask[:, :, start:end, :end]
        weights = nn.functional.softmax(weights, dim=-1, dtype=torch.float32).to(query.dtype)
        outputs.append(torch.matmul(weights, value[:, :, :end]))
    return torch.cat(outputs, dim=2).transpose(1, 2).contiguous(), None


AttentionInterface.register(HALVES, causal_halves_attention)
AttentionMaskInterface.register(HALVES, eager_mask)  # the masks eager attention gets


@contextmanager
def attention_halves(model: PreTrainedModel, enabled: bool):
    """While the block runs, ``model`` attends with `causal_halves_attention` where ``enabled`` and the model
    attends eagerly with transformers' generic eager attention (`GENERIC_EAGER_MODELS`); afterwards its attention
    is what it was (so the saved model's config says ``eager``). Otherwise nothing changes; a model this cannot
    serve gets one warning naming why."""
    config = model.config
    before = config._attn_implementation
    use = enabled and before == "eager" and type(model).__name__ in GENERIC_EAGER_MODELS
    if enabled and not use:
        log.warning("train.attention_halves: %s attends with %r; halves need eager attention in one of %s: it "
                    "keeps its own", type(model).__name__, before, ", ".join(GENERIC_EAGER_MODELS))
    if not use:
        yield
        return
    config._attn_implementation = HALVES
    try:
        yield
    finally:
        config._attn_implementation = before
