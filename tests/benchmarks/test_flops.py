"""The FLOP counters the training benchmark reports (benchmarks/flops.py)."""

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from flops import count_parameters, training_flops, training_flops_per_token  # noqa: E402

from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import build_scratch_model  # noqa: E402
from pipeline.lm.tokenizer import build_word_tokenizer  # noqa: E402

TINY = dict(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, max_length=256)


@pytest.fixture(scope="module")
def tokenizer():
    return build_word_tokenizer(["Grid is from (0, 0) to (3, 2).\nup down cut"], frame=5)


def test_flops_count_weights_and_causal_attention(tokenizer):
    model = build_scratch_model(tokenizer, ModelSettings(**TINY))
    n = count_parameters(model)  # tied embeddings: the output head is a matmul over the shared matrix
    assert n == sum(p.numel() for p in model.parameters())
    assert training_flops_per_token(model, 0) == 6 * n
    assert training_flops_per_token(model, 10) == 6 * n + 12 * 2 * 32 * 10
    assert training_flops(model, [3]) == 3 * training_flops_per_token(model, 2)
