"""Small conversations and their tokenizer, shared by this folder's training tests (import `data` as a fixture)."""
import random

import pytest
import torch

from pipeline.lm.chat import WORD_LEVEL_FORMAT
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import build_scratch_model, load_model
from pipeline.lm.tokenizer import build_word_tokenizer
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.trainer import finetune

TINY = dict(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, max_length=512)


def conversation(rng):
    """A small Gridworld-like conversation (a prompt and a Thought/Plan answer) drawn from ``rng``."""
    x, y = rng.randint(2, 6), rng.randint(2, 6)
    thought = "\n".join(f"Step {k}:\n({rng.randint(0, x)}, {rng.randint(0, y)})\n{rng.choice(['up', 'cut'])}"
                        for k in range(1, rng.randint(2, 7)))
    return [{"from": "human", "value": f"Grid is from (0, 0) to ({x}, {y}). Goal: ({x}, {y})"},
            {"from": "gpt", "value": f"Thought:\n{thought}\nPlan:\nup"}]


@pytest.fixture(scope="module")
def data():
    """40 such conversations and a word-level tokenizer built on them."""
    rng = random.Random(0)
    conversations = [conversation(rng) for _ in range(40)]
    return conversations, build_word_tokenizer(t["value"] for c in conversations for t in c)


def trained(data, out, **settings):
    """A TINY scratch model (seed 0) fine-tuned on ``data`` with ``settings`` into ``out``: the result and the
    saved weights."""
    conversations, tokenizer = data
    model = build_scratch_model(tokenizer, ModelSettings(**TINY), seed=0)
    result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations, TrainSettings(**settings), out)
    return result, load_model(result.model_dir).state_dict()


def assert_same_loss_and_gradients(model, own, ours):
    """The loss ``ours()`` computes, and its gradients on ``model``, are those of ``own()`` (each a callable that
    returns a loss of ``model``)."""
    def loss_and_grads(compute):
        model.zero_grad(set_to_none=True)
        loss = compute()
        loss.backward()
        return loss.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}

    own_loss, own_grads = loss_and_grads(own)
    our_loss, our_grads = loss_and_grads(ours)
    assert torch.allclose(our_loss, own_loss, rtol=1e-6)
    # The same sums in another order: fp32 rounding is relative to a tensor's largest terms, not to each element
    # (an AVX2-only CPU's kernels put a tied embedding's element of 1.5e-3 1.5e-7 apart, its largest being 0.84).
    for name, grad in own_grads.items():
        assert torch.allclose(our_grads[name], grad, rtol=1e-5, atol=1e-6 * grad.abs().max().item()), name
