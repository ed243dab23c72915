"""The last decoder layer computed from the first trained position on (`TrainSettings.labelled_last_layer`)."""

import pytest
import torch

from pipeline.lm.chat import IGNORE_INDEX, WORD_LEVEL_FORMAT
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import build_scratch_model, load_model
from grid_conversations import TINY, assert_same_loss_and_gradients, data  # noqa: F401 - data: a fixture
from pipeline.lm.training import last_layer
from pipeline.lm.training import trainer as trainer_module
from pipeline.lm.training.batches import stretched_batch_positions
from pipeline.lm.training.last_layer import hidden_from, not_cut, start_of_labels, trims
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.trainer import finetune, labelled_loss


def model(tokenizer, attention="eager"):
    return build_scratch_model(tokenizer, ModelSettings(**TINY, attn_implementation=attention), seed=0)


def batch(vocab: int) -> dict:
    """Three right-padded rows whose answers start at different positions, with stretched positions."""
    generator = torch.Generator().manual_seed(0)
    ids = torch.randint(1, vocab, (3, 14), generator=generator)
    labels = ids.clone()
    labels[0, :6] = IGNORE_INDEX       # a prompt of 6
    labels[1, :8] = IGNORE_INDEX       # a longer one
    labels[1, 11:] = IGNORE_INDEX      # and padding
    labels[2, :] = IGNORE_INDEX        # a row with nothing to learn
    mask = torch.ones_like(ids)
    mask[1, 11:] = 0
    return {"input_ids": ids, "labels": labels, "attention_mask": mask,
            "position_ids": stretched_batch_positions(mask, 2.0, seed=3)}


def test_the_start_is_the_first_position_any_row_trains_on(data):
    inputs = batch(len(data[1]))
    keep = inputs["labels"][:, 1:] != IGNORE_INDEX
    assert start_of_labels(keep) == 5  # row 0's first label is at 6: its logits come from position 5
    assert start_of_labels(torch.zeros(2, 7, dtype=torch.bool)) == 0
    assert start_of_labels(torch.zeros(0, 7, dtype=torch.bool)) == 0


@pytest.mark.parametrize("start", [0, 5, 12])
def test_hidden_states_from_a_start_are_the_models_own_there(data, start):
    net = model(data[1])
    inputs = {k: v for k, v in batch(len(data[1])).items() if k != "labels"}
    with torch.no_grad():
        own = net.base_model(**inputs).last_hidden_state
        ours = hidden_from(net.base_model, inputs, start)
        plain = hidden_from(net.base_model, {"input_ids": inputs["input_ids"]}, start)  # no mask, plain positions
        plain_own = net.base_model(input_ids=inputs["input_ids"]).last_hidden_state
    assert ours.shape == (3, 14 - start, TINY["hidden_size"])
    assert torch.allclose(ours, own[:, start:], atol=1e-5)
    assert torch.allclose(plain, plain_own[:, start:], atol=1e-5)


@pytest.mark.parametrize("num_items", [None, 7])
def test_the_loss_with_the_last_layer_cut_is_the_models_own_with_its_gradients(data, num_items):
    net = model(data[1])
    assert trims(net.base_model)
    inputs = batch(len(data[1]))

    assert_same_loss_and_gradients(net, lambda: net(**inputs, num_items_in_batch=num_items).loss,
                                   lambda: labelled_loss(net, inputs, num_items, last_layer=True))


def test_a_model_with_sdpa_attention_runs_its_whole_last_layer(data, monkeypatch):
    net = model(data[1], "sdpa")
    assert not trims(net.base_model)
    monkeypatch.setattr(trainer_module, "hidden_from", lambda *a: pytest.fail("the last layer was cut"))
    inputs = batch(len(data[1]))
    assert torch.allclose(labelled_loss(net, inputs, last_layer=True), net(**inputs).loss, rtol=1e-6)


def test_training_with_the_last_layer_cut_trains_what_the_whole_model_trains(data, tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(trainer_module, "hidden_from",
                        lambda *args: calls.append(args[2]) or last_layer.hidden_from(*args))
    settings = dict(max_steps=6, report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2,
                    per_device_batch_size=4, torch_threads=2, optimizer="muon", position_stretch=2.0,
                    labelled_logits=True, batch_threads=2)

    def run(name, **extra):
        conversations, tokenizer = data
        result = finetune(model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, conversations,
                          TrainSettings(**settings, **extra), tmp_path / name)
        return result, load_model(result.model_dir).state_dict()

    whole, w = run("whole")
    assert calls == []
    cut, c = run("cut", labelled_last_layer=True)
    assert len(calls) == 12 and all(start > 0 for start in calls)  # every part of every step, its prompt left out
    assert cut.final_loss == pytest.approx(whole.final_loss, rel=1e-4)
    assert all(torch.allclose(w[k], c[k], atol=1e-4) for k in w)


def test_the_switch_is_off_without_labelled_logits():
    assert TrainSettings(labelled_logits=True, labelled_last_layer=True).labelled_last_layer
    assert not TrainSettings(labelled_last_layer=True).labelled_last_layer


def test_a_model_whose_last_layer_is_not_cut_is_named_once(data, tmp_path, caplog):
    conversations, tokenizer = data
    settings = TrainSettings(max_steps=1, report_to=(), save_steps=100, per_device_batch_size=4, labelled_logits=True,
                             labelled_last_layer=True)
    with caplog.at_level("WARNING"):
        finetune(model(tokenizer, "sdpa"), tokenizer, WORD_LEVEL_FORMAT, conversations, settings, tmp_path)
    assert sum("LlamaModel with sdpa attention is not a model whose last layer is cut" in r.message
               and "its last layer runs at every position" in r.message for r in caplog.records) == 1
    assert "compiled stacked, is not" in not_cut(model(tokenizer).base_model, stacked=True)
    assert not_cut(model(tokenizer).base_model, stacked=False) is None
