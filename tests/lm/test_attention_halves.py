"""Causal attention in two halves of its queries while training (`TrainSettings.attention_halves`)."""

import pytest
import torch
from transformers import AttentionInterface

from pipeline.lm.chat import WORD_LEVEL_FORMAT
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import build_scratch_model, load_model
from grid_conversations import TINY, data, trained  # noqa: F401 - data: a fixture
from pipeline.lm.training import attention
from pipeline.lm.training.attention import HALVES, attention_halves, causal_halves_attention
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.trainer import finetune

EAGER = dict(TINY, attn_implementation="eager")


def padded_batch(vocab: int) -> dict:
    generator = torch.Generator().manual_seed(0)
    ids = torch.randint(1, vocab, (3, 13), generator=generator)  # an odd length: halves of 6 and 7 queries
    mask = torch.ones_like(ids)
    mask[1, 9:] = 0  # right padding
    return {"input_ids": ids, "attention_mask": mask, "labels": ids.masked_fill(mask == 0, -100)}


def loss_and_grads(model, inputs):
    model.zero_grad(set_to_none=True)
    loss = model(**inputs).loss
    loss.backward()
    return loss.detach(), {n: p.grad.clone() for n, p in model.named_parameters()}


def test_halves_compute_the_eager_attention_and_its_gradients(data):
    _, tokenizer = data
    model = build_scratch_model(tokenizer, ModelSettings(**EAGER), seed=0)
    inputs = padded_batch(len(tokenizer))
    eager, eager_grads = loss_and_grads(model, inputs)
    with attention_halves(model, True):
        assert model.config._attn_implementation == HALVES
        halves, halves_grads = loss_and_grads(model, inputs)
    assert model.config._attn_implementation == "eager"
    assert torch.allclose(halves, eager, rtol=1e-6)
    assert all(torch.allclose(halves_grads[n], eager_grads[n], atol=1e-7) for n in eager_grads)


def test_decoding_with_a_cache_attends_as_eager_does(data):
    _, tokenizer = data
    model = build_scratch_model(tokenizer, ModelSettings(**EAGER), seed=0).eval()
    prompt = padded_batch(len(tokenizer))["input_ids"][:1, :8]
    settings = dict(max_new_tokens=6, do_sample=False, pad_token_id=tokenizer.pad_token_id)
    eager = model.generate(prompt, **settings)
    calls = []

    def counted(module, query, key, *args, **kwargs):
        calls.append(query.shape[2] == key.shape[2])
        return causal_halves_attention(module, query, key, *args, **kwargs)

    AttentionInterface.register(HALVES, counted)
    try:
        with attention_halves(model, True):
            halves = model.generate(prompt, **settings)
    finally:
        AttentionInterface.register(HALVES, causal_halves_attention)
    assert torch.equal(halves, eager)
    assert True in calls and False in calls  # the prompt in halves, each new token against the cache


def test_training_with_halves_trains_what_eager_attention_trains(data, tmp_path, monkeypatch):
    calls = []

    def counted(module, query, key, *args, **kwargs):
        calls.append(query.shape[2])
        return causal_halves_attention(module, query, key, *args, **kwargs)

    conversations, tokenizer = data
    settings = dict(max_steps=4, report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2,
                    per_device_batch_size=4, torch_threads=2, optimizer="muon", position_stretch=2.0,
                    batch_threads=2, labelled_logits=True)

    def run(name, **extra):
        model = build_scratch_model(tokenizer, ModelSettings(**EAGER), seed=0)
        result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations, TrainSettings(**settings, **extra),
                          tmp_path / name)
        assert model.config._attn_implementation == "eager"
        return result, load_model(result.model_dir)

    AttentionInterface.register(HALVES, counted)
    try:
        eager, eager_model = run("eager")
        assert calls == []
        halves, halves_model = run("halves", attention_halves=True)
    finally:
        AttentionInterface.register(HALVES, causal_halves_attention)
    assert len(calls) == 4 * 2 * TINY["num_layers"]  # every step, part and layer
    assert HALVES not in (tmp_path / "halves" / "model" / "config.json").read_text()  # saved as it was built
    assert halves.final_loss == pytest.approx(eager.final_loss, rel=1e-4)
    weights = eager_model.state_dict()
    assert all(torch.allclose(weights[k], v, atol=1e-4) for k, v in halves_model.state_dict().items())


def test_a_model_without_generic_eager_attention_keeps_its_own(data, tmp_path, caplog, monkeypatch):
    monkeypatch.setattr(attention, "causal_halves_attention", lambda *a, **k: pytest.fail("halves were used"))
    with caplog.at_level("WARNING"):
        trained(data, tmp_path / "sdpa", max_steps=1, report_to=(), save_steps=100, per_device_batch_size=4,
                attention_halves=True)  # TINY attends with sdpa
    assert sum("halves need eager attention" in r.message for r in caplog.records) == 1


def test_muon_precision_is_off_without_muon():
    assert TrainSettings(optimizer="muon", muon_bf16=True).muon_bf16
    assert not TrainSettings(optimizer="adamw", muon_bf16=True).muon_bf16
