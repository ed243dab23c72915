"""The output head and loss at the labelled positions only (`TrainSettings.labelled_logits`)."""

import pytest
import torch

from pipeline.lm.chat import IGNORE_INDEX, WORD_LEVEL_FORMAT
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import build_scratch_model
from grid_conversations import TINY, assert_same_loss_and_gradients, data, trained  # noqa: F401 - data: a fixture
from pipeline.lm.training.settings import SettingError, TrainSettings
from pipeline.lm.training import trainer as trainer_module
from pipeline.lm.training.trainer import finetune, labelled_loss



def inputs_with_unlabelled_positions(vocab: int) -> dict:
    generator = torch.Generator().manual_seed(0)
    ids = torch.randint(1, vocab, (3, 12), generator=generator)
    labels = ids.clone()
    labels[:, :5] = IGNORE_INDEX      # a prompt
    labels[1, 9:] = IGNORE_INDEX      # padding
    labels[2, :] = IGNORE_INDEX       # a row with nothing to learn
    mask = torch.ones_like(ids)
    mask[1, 9:] = 0
    return {"input_ids": ids, "labels": labels, "attention_mask": mask}


@pytest.mark.parametrize("num_items", [None, 7])
def test_labelled_loss_is_the_models_own_loss_with_its_gradients(data, num_items):
    _, tokenizer = data
    model = build_scratch_model(tokenizer, ModelSettings(**TINY), seed=0)
    inputs = inputs_with_unlabelled_positions(len(tokenizer))

    assert_same_loss_and_gradients(model, lambda: model(**inputs, num_items_in_batch=num_items).loss,
                                   lambda: labelled_loss(model, inputs, num_items))


def test_a_batch_without_labelled_positions_has_zero_loss_and_gradients(data):
    _, tokenizer = data
    model = build_scratch_model(tokenizer, ModelSettings(**TINY), seed=0)
    inputs = inputs_with_unlabelled_positions(len(tokenizer))
    inputs["labels"] = torch.full_like(inputs["labels"], IGNORE_INDEX)
    loss = labelled_loss(model, inputs, 5)
    loss.backward()
    assert loss.item() == 0 and all(not p.grad.any() for p in model.parameters())


def test_training_with_labelled_logits_trains_what_the_full_head_trains(data, tmp_path, monkeypatch):
    calls = []

    def counted(*args, **kwargs):
        calls.append(args[1]["input_ids"].shape[0])
        return labelled_loss(*args, **kwargs)

    monkeypatch.setattr(trainer_module, "labelled_loss", counted)
    settings = dict(max_steps=6, report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2,
                    per_device_batch_size=4, torch_threads=2, optimizer="muon", position_stretch=2.0)

    def run(name, **extra):
        return trained(data, tmp_path / name, **settings, **extra)

    full, f = run("full")
    assert calls == []
    labelled, lab = run("labelled", labelled_logits=True)
    assert calls == [4] * 6  # every micro-batch of every step
    parts, p = run("parts", labelled_logits=True, batch_threads=2)
    assert calls[6:] == [2] * 12  # and every part of them
    assert labelled.final_loss == pytest.approx(full.final_loss, rel=1e-4)
    assert all(torch.allclose(f[k], lab[k], atol=1e-4) for k in f)
    assert parts.final_loss == pytest.approx(full.final_loss, rel=1e-4)
    assert all(torch.allclose(f[k], p[k], atol=1e-4) for k in f)


def test_labelled_logits_with_accelerate_are_refused_naming_the_value():
    with pytest.raises(SettingError, match="labelled_logits=True.*false with accelerate_config"):
        TrainSettings(labelled_logits=True, accelerate_config="fsdp.yaml")


def test_a_model_whose_logits_are_not_its_heads_output_keeps_its_own_loss(data, tmp_path, monkeypatch, caplog):
    conversations, tokenizer = data
    monkeypatch.setattr(trainer_module, "PLAIN_HEAD_MODELS", ("SomeOtherForCausalLM",))
    monkeypatch.setattr(trainer_module, "labelled_loss", lambda *a, **k: pytest.fail("labelled_loss was used"))
    model = build_scratch_model(tokenizer, ModelSettings(**TINY), seed=0)
    settings = TrainSettings(max_steps=2, report_to=(), save_steps=100, per_device_batch_size=4, labelled_logits=True)
    with caplog.at_level("WARNING"):
        finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations, settings, tmp_path)
    assert sum("its own forward computes the loss instead" in r.message for r in caplog.records) == 1
