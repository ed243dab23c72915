import gc
import json
import math
import os
import random
import threading

import mlflow
import pytest
import torch
from transformers import DataCollatorWithFlattening, Trainer, TrainerCallback

from pipeline.lm.chat import IGNORE_INDEX, WORD_LEVEL_FORMAT
from pipeline.workflow.config import PYTHON_H, cxx_compiler
from pipeline.lm.training.batches import (
    LengthGroupedBatches, RightPadCollator, stretched_batch_positions, stretched_positions, tokenize_conversations,
)
from pipeline.lm.training.compile import cpu_has_bf16, dynamo_environment as _dynamo_environment
from pipeline.lm.training.entry import TrainRequest, main
from pipeline.lm.training.parts import PartThreads
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.result import RESULT_FILE
from pipeline.lm.training.trainer import _training_arguments, finetune
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import ComposedRows, build_scratch_model, load_chat_format, load_model
from pipeline.lm.tokenizer import build_word_tokenizer

TINY = dict(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, max_length=512)
# One thread: tiny models gain nothing from two, and lose a lot when the machine is shared.
QUIET = dict(report_to=(), logging_steps=1, save_steps=100, learning_rate=1e-2, per_device_batch_size=4,
             torch_threads=1)


def conversation(rng: random.Random) -> list[dict]:
    """A conversation in the shape of the core's texts: a task, a map of random length and a plan."""
    x, y = rng.randint(2, 6), rng.randint(2, 6)
    steps = rng.randint(1, 6)
    thought = "\n".join(f"Step {k}:\n({rng.randint(0, x)}, {rng.randint(0, y)})\n{rng.choice(['up', 'cut'])}"
                        for k in range(1, steps + 1))
    plan = "\n".join(rng.choice(["up", "right"]) for _ in range(rng.randint(2, 5)))
    return [
        {"from": "human", "value": "Answer with moves."},
        {"from": "gpt", "value": "OK"},
        {"from": "human", "value": f"Grid is from (0, 0) to ({x}, {y}). Goal: ({x}, {y})\nCurrent: (0, 0)"},
        {"from": "gpt", "value": f"Thought:\n{thought}\nPlan:\n{plan}"},
    ]


@pytest.fixture(scope="module")
def conversations():
    rng = random.Random(0)
    return [conversation(rng) for _ in range(48)]


@pytest.fixture(scope="module")
def tokenizer(conversations):
    return build_word_tokenizer(turn["value"] for turns in conversations for turn in turns)


def tiny_model(tokenizer):
    return build_scratch_model(tokenizer, ModelSettings(**TINY), seed=0)


@pytest.mark.parametrize("bad, match", [
    (dict(max_steps=0), "max_steps=0"),
    (dict(per_device_batch_size=0), "per_device_batch_size=0"),
    (dict(lr_scheduler_type="cosin"), "lr_scheduler_type='cosin'.*cosine"),
    (dict(warmup_ratio=1.5), "warmup_ratio=1.5"),
    (dict(report_to=("wandb",)), "report_to=\\['wandb'\\].*mlflow"),
    (dict(eval_fraction=1.0), "eval_fraction=1.0"),
    (dict(torch_threads=0), "torch_threads=0"),
    (dict(pad_to_multiple_of=0), "pad_to_multiple_of=0"),
    (dict(optimizer="sgd"), "optimizer='sgd'.*adamw, muon"),
    (dict(optimizer="muon", accelerate_config="fsdp.yaml"), "optimizer='muon'.*adamw when accelerate_config"),
])
def test_settings_reject_bad_values(bad, match):
    with pytest.raises(ValueError, match=match):
        TrainSettings(**bad)


def test_settings_from_dict_refuses_unknown_keys():
    assert TrainSettings.from_dict({"max_steps": 3, "report_to": []}).report_to == []
    with pytest.raises(ValueError, match="unknown train settings \\['learnig_rate'\\]"):
        TrainSettings.from_dict({"learnig_rate": 1e-3})


def test_labels_cover_gpt_values_and_turn_ends_only(tokenizer, conversations):
    data = tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations[:3], max_length=512)
    end = tokenizer.encode(WORD_LEVEL_FORMAT.turn_end, add_special_tokens=False)
    for turns, example in zip(conversations, data):
        targets = [t for t in example["labels"] if t != IGNORE_INDEX]
        expected = []
        for turn in turns:
            if turn["from"] == "gpt":
                expected += tokenizer.encode(turn["value"], add_special_tokens=False) + end
        assert targets == expected
        kept = [i for i, t in zip(example["input_ids"], example["labels"]) if t != IGNORE_INDEX]
        assert kept == targets  # a label is the token at its own position (the model shifts)


def test_too_long_conversations_are_dropped_and_counted(tokenizer, conversations):
    lengths = tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations, 10_000).lengths
    limit = sorted(lengths)[len(lengths) // 2]
    data = tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations, limit)
    assert data.dropped == sum(n > limit for n in lengths) > 0
    assert len(data) + data.dropped == len(conversations)
    assert max(data.lengths) <= limit


def test_too_long_conversations_are_truncated_when_asked_and_counted(tokenizer, conversations, caplog):
    full = tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations, 10_000)
    limit = sorted(full.lengths)[len(full) // 2]
    with caplog.at_level("WARNING", logger="pipeline.lm.training.batches"):
        data = tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations, limit, "truncate")
    over = sum(n > limit for n in full.lengths)
    assert (data.truncated, data.dropped, len(data)) == (over, 0, len(conversations))
    for whole, cut in zip(full, data):
        assert cut["input_ids"] == whole["input_ids"][:limit] and cut["labels"] == whole["labels"][:limit]
    assert f"training: {over} of {len(conversations)} conversations are longer than max_length={limit} tokens " \
           f"(train.long_conversations=truncate): {over} truncated to their first {limit} tokens, 0 dropped" in caplog.text
    # Cut before its first target (inside the prompt): nothing left to train on, dropped and counted.
    prompt_only = tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations, 5, "truncate")
    assert (len(prompt_only), prompt_only.dropped, prompt_only.truncated) == (0, len(conversations), 0)
    with pytest.raises(ValueError, match="long_conversations='cut'; allowed: drop, truncate"):
        tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations, limit, "cut")


def test_the_paper_recipe_truncates_as_the_papers_code_with_the_real_tokenizer(llama3_tokenizer):
    # Maps of 20 x 20 worlds run past the paper's context of 8,192 tokens: the paper's code cuts them there
    # and trains on the targets left (issue 24: the project dropped them).
    from fastchat_reference import fastchat_ids_and_labels, paper_conversations, paper_format

    fmt = paper_format()
    conversations = paper_conversations(2, prompts=("paper",), sizes=(18, 20))
    data = tokenize_conversations(llama3_tokenizer, fmt, conversations, 8192, "truncate")
    dropped = tokenize_conversations(llama3_tokenizer, fmt, conversations, 8192, "drop")
    assert data.truncated == dropped.dropped > 0 and data.dropped == 0
    assert [(e["input_ids"], e["labels"]) for e in data] == [
        fastchat_ids_and_labels(llama3_tokenizer, turns, 8192) for turns in conversations]
    assert max(data.lengths) == 8192


@pytest.mark.parametrize("pad", [None, -1, "<pad>"])
def test_a_collator_without_a_pad_id_is_refused_naming_the_value(pad):
    with pytest.raises(ValueError, match=f"pad_token_id={pad!r}: expected a token id.*with_pad_token"):
        RightPadCollator(pad)


@pytest.mark.parametrize("n", [2000, 2008])  # 2008: the last megabatch ends in a short batch of 8
def test_length_grouped_batches_are_tight_and_shuffled(n):
    rng = random.Random(0)
    lengths = [rng.randint(300, 1500) for _ in range(n)]  # the spread of real conversations
    torch.manual_seed(0)
    order = list(LengthGroupedBatches(lengths, batch_size=16))
    assert sorted(order) == list(range(n))
    batches = [order[i:i + 16] for i in range(0, n, 16)]  # as the data loader cuts them
    computed = sum(len(b) * max(lengths[i] for i in b) for b in batches)
    assert sum(lengths) / computed > 0.95
    longest = [max(lengths[i] for i in b) for b in batches[:50]]
    assert longest != sorted(longest) and longest != sorted(longest, reverse=True)  # no length curriculum
    assert list(LengthGroupedBatches(lengths, 16)) != order  # a new draw each epoch


def alone_logits(model, examples):
    return [model(input_ids=torch.tensor([e["input_ids"]])).logits[0] for e in examples]


@torch.no_grad()
@pytest.mark.parametrize("multiple", [1, 8])
def test_right_padded_batch_without_mask_equals_each_sequence_alone(tokenizer, conversations, multiple):
    model = tiny_model(tokenizer).eval()
    examples = list(tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations[:4], 512))
    assert len({len(e["input_ids"]) for e in examples}) > 1
    batch = RightPadCollator(tokenizer.pad_token_id, pad_to_multiple_of=multiple)(examples)
    assert "attention_mask" not in batch
    longest = max(len(e["input_ids"]) for e in examples)
    assert batch["input_ids"].shape[1] == -(-longest // multiple) * multiple
    logits = model(input_ids=batch["input_ids"]).logits
    for row, (example, alone) in enumerate(zip(examples, alone_logits(model, examples))):
        torch.testing.assert_close(logits[row, : len(example["input_ids"])], alone, atol=1e-5, rtol=1e-5)


def test_stretched_positions_are_an_ordered_subset_of_a_longer_range_and_plain_at_stretch_one():
    generator = torch.Generator().manual_seed(0)
    assert stretched_positions(50, 1.0, generator).tolist() == list(range(50))
    draws = [stretched_positions(50, 3.0, generator) for _ in range(200)]
    for positions in draws:
        assert len(positions) == 50 and bool((positions.diff() > 0).all()) and 0 <= positions[0]
        assert positions[-1] < 150
    spans = [int(p[-1]) + 1 for p in draws]
    assert min(spans) < 70 and max(spans) > 130   # the stretch is drawn over [1, 3]
    again = torch.Generator().manual_seed(0)
    stretched_positions(50, 1.0, again)
    assert torch.equal(stretched_positions(50, 3.0, again), draws[0])   # seeded


@pytest.mark.parametrize("stretch", [0.5, float("nan")])
def test_a_stretch_below_one_is_refused_naming_the_value(stretch):
    with pytest.raises(Exception, match="position_stretch=.*expected a number >= 1"):
        TrainSettings(position_stretch=stretch)


@pytest.mark.parametrize("rows", [[5, 9, 9, 1], [0, 7, 3], [16, 16]])
def test_stretched_batch_positions_are_each_rows_draws_in_turn_and_the_padding_numbered_on(rows):
    """The batch's positions are `stretched_positions` drawn row after row from the seed's generator, each row's
    padding numbered on after its last position (a row of padding alone: 0, 1, ...)."""
    width = 16
    mask = (torch.arange(width) < torch.tensor(rows)[:, None]).long()
    generator = torch.Generator().manual_seed(7)
    expected = torch.arange(width).repeat(len(rows), 1)
    for row, n in enumerate(rows):
        if n:
            expected[row, :n] = stretched_positions(n, 2.0, generator)
            expected[row, n:] = expected[row, n - 1] + 1 + torch.arange(width - n)
    assert torch.equal(stretched_batch_positions(mask, 2.0, seed=7), expected)
    assert stretched_batch_positions(mask[:, :0], 2.0, seed=7).shape == (len(rows), 0)  # no column at all


@torch.no_grad()
def test_stretched_positions_reach_each_sequence_as_if_it_were_alone(tokenizer, conversations):
    """Stretched position ids with the collator's attention mask: each row computes what the sequence computes
    alone at those positions (no jump is read as a packed sequence's start), and differs from the plain
    positions' logits; without the mask, transformers cuts the rows at the jumps."""
    model = tiny_model(tokenizer).eval()
    examples = list(tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations[:4], 512))
    batch = RightPadCollator(tokenizer.pad_token_id, attention_mask=True, pad_to_multiple_of=8)(examples)
    mask = batch["attention_mask"]
    positions = stretched_batch_positions(mask, 2.0, seed=3)
    assert torch.equal(stretched_batch_positions(mask, 2.0, seed=3), positions)   # the seed alone decides
    assert not torch.equal(stretched_batch_positions(mask, 2.0, seed=4), positions)
    assert positions.shape == mask.shape == batch["input_ids"].shape
    assert bool((positions.diff(dim=1) > 0).all())
    # use_cache=False as in Trainer: the case in which transformers looks for packed sequences in the positions
    logits = model(input_ids=batch["input_ids"], position_ids=positions, attention_mask=mask, use_cache=False).logits
    maskless = model(input_ids=batch["input_ids"], position_ids=positions, use_cache=False).logits
    jumps = 0
    for row, (example, plain) in enumerate(zip(examples, alone_logits(model, examples))):
        n = len(example["input_ids"])
        assert mask[row].sum() == n and positions[row, n - 1] >= n - 1
        alone = model(input_ids=torch.tensor([example["input_ids"]]), position_ids=positions[row:row + 1, :n]).logits[0]
        torch.testing.assert_close(logits[row, :n], alone, atol=1e-5, rtol=1e-5)
        if positions[row, n - 1] > n - 1:   # a jump: without the mask the row is cut into "sequences"
            jumps += 1
            assert not torch.allclose(maskless[row, :n], alone, atol=1e-4)
            assert not torch.allclose(alone, plain, atol=1e-4)
    assert jumps >= 2
    assert set(RightPadCollator(tokenizer.pad_token_id)(examples)) == {"input_ids", "labels"}


def test_stretched_positions_reach_training_and_only_training(tokenizer, conversations, tmp_path):
    """``position_stretch`` changes what a step computes (the trainer passes the drawn positions), and the
    held-out accuracy, scored at plain positions, runs as before."""
    runs = {stretch: finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, conversations[:16],
                              TrainSettings(max_steps=3, eval_fraction=0.25, position_stretch=stretch, **QUIET),
                              tmp_path / str(stretch))
            for stretch in (1.0, 3.0)}
    plain, stretched = (load_model(runs[s].model_dir) for s in (1.0, 3.0))
    assert any(not torch.equal(a, b) for a, b in zip(plain.state_dict().values(), stretched.state_dict().values()))
    assert runs[3.0].token_accuracy is not None and runs[3.0].tokens_trained == runs[1.0].tokens_trained


@torch.no_grad()
def test_flattened_batch_is_exact_only_without_a_cache(tokenizer, conversations):
    """transformers 5 reads restarting position ids as a block-diagonal mask, but only when no KV cache is
    made: with ``use_cache=True`` (the config default outside Trainer) sequences silently see each other."""
    model = tiny_model(tokenizer).eval()
    examples = list(tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations[:3], 512))
    batch = DataCollatorWithFlattening()(examples)

    def flat_logits(use_cache):
        return model(input_ids=batch["input_ids"], position_ids=batch["position_ids"], use_cache=use_cache).logits[0]

    exact, leaky = flat_logits(False), flat_logits(True)
    start = 0
    for example, alone in zip(examples, alone_logits(model, examples)):
        n = len(example["input_ids"])
        torch.testing.assert_close(exact[start:start + n], alone, atol=1e-5, rtol=1e-5)
        if start:
            assert not torch.allclose(leaky[start:start + n], alone, atol=1e-3)
        start += n


@pytest.mark.parametrize("optimizer", ["adamw", "muon"])
def test_loss_falls_and_held_out_tokens_are_learned(tokenizer, conversations, tmp_path, optimizer):
    repeated = conversations[:2] * 24
    settings = TrainSettings(max_steps=30, eval_fraction=0.25, optimizer=optimizer, **QUIET)
    result = finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, repeated, settings, tmp_path)
    assert result.final_loss < 0.5 * math.log(len(tokenizer))
    assert result.token_accuracy > 0.4  # chance is 1/len(tokenizer), under 0.02
    assert result.global_step == 30
    assert result.tokens_trained > 0 and result.tokens_per_second > 0


@pytest.mark.parametrize("optimizer, parts", [("adamw", 1), ("muon", 1), ("muon", 2)])
def test_composed_newlines_train_and_stay_composed(conversations, tmp_path, optimizer, parts):
    """newlines=composed: training moves the words' and the newline's rows and keeps every joined row their sum,
    in the model trained and the model saved (a plain Llama); the same model without it trains its own rows.
    With Muon the rows are written during its step (on the part threads' time with parts)."""
    tokenizer = build_word_tokenizer((turn["value"] for turns in conversations for turn in turns), newlines="composed")
    rows = ComposedRows.of(tokenizer)
    model = build_scratch_model(tokenizer, ModelSettings(**TINY, newlines="composed"), seed=0)
    before = model.get_input_embeddings().weight.detach().clone()
    settings = TrainSettings(max_steps=12, optimizer=optimizer, batch_threads=parts, **{**QUIET, "torch_threads": 2})
    result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations, settings, tmp_path)
    for weight in (model.get_input_embeddings().weight, load_model(result.model_dir).get_input_embeddings().weight):
        torch.testing.assert_close(weight[rows.joined], weight[rows.words] + weight[rows.newline], atol=1e-6, rtol=0)
    after = model.get_input_embeddings().weight
    assert not torch.allclose(after[rows.newline], before[rows.newline]) and not torch.allclose(after[rows.words],
                                                                                                 before[rows.words])
    assert result.global_step == 12
    ids = torch.tensor([tokenizer("Goal: (1, 2)\nup")["input_ids"]])
    model.zero_grad()
    model(input_ids=ids, labels=ids).loss.backward()   # after training the hook is gone: joined rows get gradient
    assert after.grad[rows.joined].abs().sum() > 0
    plain = build_scratch_model(tokenizer, ModelSettings(**TINY, newlines="joined"), seed=0)
    finetune(plain, tokenizer, WORD_LEVEL_FORMAT, conversations, settings, tmp_path / "plain")
    weight = plain.get_input_embeddings().weight
    assert not torch.allclose(weight[rows.joined], weight[rows.words] + weight[rows.newline], atol=1e-3)


def test_precision_and_compile_settings_reach_the_trainer(tmp_path):
    plain = _training_arguments(TrainSettings(**QUIET), tmp_path, 0)
    assert not plain.bf16 and not plain.torch_compile
    with _dynamo_environment():
        tuned = _training_arguments(TrainSettings(bf16=True, torch_compile="full", **QUIET), tmp_path, 0)
        regional = _training_arguments(TrainSettings(torch_compile="regional", **QUIET), tmp_path, 0)
    assert tuned.bf16 == (torch.cuda.is_available() or cpu_has_bf16()) and tuned.torch_compile
    assert not regional.torch_compile  # compiled in place by finetune, not by Trainer
    assert tuned.use_cpu == (tuned.bf16 and not torch.cuda.is_available())  # bf16 without a GPU is CPU autocast


def test_bf16_on_a_cpu_without_bf16_hardware_falls_back_to_fp32(tmp_path, monkeypatch, caplog):
    amd_avx2 = "processor\t: 0\nflags\t\t: fpu sse2 avx avx2 fma\n"
    zen5 = "flags\t\t: fpu avx2 avx512f avx512_bf16 avx512_vnni\n"
    xeon = "flags\t\t: fpu avx2 avx512f amx_bf16 amx_tile\n"
    assert (cpu_has_bf16(amd_avx2), cpu_has_bf16(zen5), cpu_has_bf16(xeon)) == (False, True, True)
    assert cpu_has_bf16("Features\t: fp asimd bf16\n")  # no x86 flags line: trusted
    monkeypatch.setattr("pipeline.lm.training.trainer.torch.cuda.is_available", lambda: False)
    monkeypatch.setattr("pipeline.lm.training.compile.cpu_has_bf16", lambda: False)
    with caplog.at_level("WARNING", logger="pipeline.lm.training.trainer"):
        arguments = _training_arguments(TrainSettings(bf16=True, **QUIET), tmp_path, 0)
    assert not arguments.bf16 and not arguments.use_cpu
    assert "no bf16 matmul hardware" in caplog.text


@pytest.mark.parametrize("fp32, bf16, chosen", [(308.0, 165.0, False), (142.0, 396.0, True), (300.0, 250.0, True)])
def test_bf16_when_faster_follows_the_measured_matmul_peaks(tmp_path, monkeypatch, caplog, fp32, bf16, chosen):
    # The first two: the two machines of docs/speed.md (Intel Xeon without AMX; AMD EPYC).
    monkeypatch.setattr("pipeline.lm.training.trainer.torch.cuda.is_available", lambda: False)
    monkeypatch.setattr("pipeline.lm.training.compile.cpu_has_bf16", lambda: True)
    monkeypatch.setattr("pipeline.lm.training.compile._PEAKS", {})  # measured once a process: these measure anew
    measured = []
    monkeypatch.setattr("pipeline.lm.training.compile.matmul_peak",
                        lambda dtype, **_: measured.append(dtype) or {torch.float32: fp32, torch.bfloat16: bf16}[dtype])
    # Without the switch the CPU's flags decide alone: bf16, nothing measured (the default recipe's numbers).
    assert _training_arguments(TrainSettings(bf16=True, **QUIET), tmp_path, 0).bf16 and not measured
    with caplog.at_level("INFO", logger="pipeline.lm.training.compile"):
        arguments = _training_arguments(TrainSettings(bf16=True, bf16_when_faster=True, **QUIET), tmp_path, 0)
    assert arguments.bf16 is chosen and arguments.use_cpu is chosen
    assert f"bf16 {bf16:.0f}, fp32 {fp32:.0f} GFLOP/s" in caplog.text
    assert ("slower than fp32" in caplog.text) is not chosen
    assert not _training_arguments(TrainSettings(bf16=False, bf16_when_faster=True, **QUIET), tmp_path, 0).bf16


@pytest.mark.parametrize("scope, backend", [("none", "NO"), ("regional", "NO"), ("full", "INDUCTOR")])
def test_the_compile_scope_reaches_accelerate_and_does_not_outlive_the_trainer(
        scope, backend, tokenizer, tmp_path, monkeypatch):
    # What an earlier compiled job (or a launcher) left in the environment must not decide this job's scope.
    monkeypatch.setenv("ACCELERATE_DYNAMO_BACKEND", "INDUCTOR")
    monkeypatch.setenv("ACCELERATE_DYNAMO_USE_REGIONAL_COMPILATION", "True")
    before = dict(os.environ)
    settings = TrainSettings(torch_compile=scope, **QUIET)
    with _dynamo_environment():
        trainer = Trainer(model=tiny_model(tokenizer), args=_training_arguments(settings, tmp_path, 0))
    plugin = trainer.accelerator.state.dynamo_plugin
    assert (plugin.backend.value, bool(getattr(plugin, "use_regional_compilation", False))) == (backend, False)
    assert dict(os.environ) == before


@pytest.mark.slow  # compiling takes about 50 s on 2 cores with an empty cache
@pytest.mark.skipif(cxx_compiler() is None or not PYTHON_H.is_file(), reason="torch.compile on a CPU needs a C++ "
                    "compiler and the Python headers")
def test_regional_compile_trains_what_eager_trains_and_saves_plain_weights(tokenizer, conversations, tmp_path):
    # A whole epoch of 46 conversations in batches of 4: batches of several widths, then one short batch of 2.
    data, steps = conversations[:46], 12
    settings = dict(max_steps=steps, pad_to_multiple_of=1, **QUIET)
    eager = finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, data, TrainSettings(**settings),
                     tmp_path / "eager")
    model, seen, shapes = tiny_model(tokenizer), [], set()
    model.model.embed_tokens.register_forward_hook(lambda module, args, out: shapes.add(tuple(out.shape[:2])))
    torch._dynamo.reset()  # no compile attempts recorded by an earlier test: a fresh process's dynamo
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    attempts = set()  # dynamo's timed compile attempts (its reset at the end clears them)

    class Compiled(TrainerCallback):
        def on_step_end(self, args, state, control, **kwargs):
            seen.append([layer._compiled_call_impl is not None for layer in model.model.layers])
            attempts.update(k for k in torch._dynamo.utils.compilation_time_metrics if k.startswith("compile_attempt"))

    compiled = finetune(model, tokenizer, WORD_LEVEL_FORMAT, data,
                        TrainSettings(torch_compile="regional", **settings), tmp_path / "compiled",
                        callbacks=[Compiled()])
    assert seen == [[True, True]] * steps  # each decoder layer compiled while training ...
    # ... once, for every width and batch size (a recompile cost the default job 15 s, and 20 s at its short batch)
    assert len({width for _, width in shapes}) > 3 and {size for size, _ in shapes} == {4, 2}
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] - graphs == 1
    # ... traced in one attempt: a float traced as a symbol made dynamo start over (3 s of each cold compile)
    assert attempts == {"compile_attempt_0"}
    assert all(layer._compiled_call_impl is None for layer in model.model.layers)  # ... and eager after
    assert compiled.final_loss == pytest.approx(eager.final_loss, rel=1e-3)
    a, b = load_model(eager.model_dir).state_dict(), load_model(compiled.model_dir).state_dict()
    assert a.keys() == b.keys()
    assert all(torch.allclose(a[k], b[k], atol=1e-3) for k in a)  # 12 steps at lr 1e-2: inductor's rounding grows


def test_eager_attention_trains_what_sdpa_trains_on_packed_batches(tokenizer, conversations, tmp_path):
    # Packed batches are right-padded with no attention mask: eager attention (the CPU default) must still be
    # causal, or its losses would part from sdpa's at the first step.
    settings = TrainSettings(max_steps=4, **QUIET)
    losses = {}
    for kernel in ("sdpa", "eager"):
        model = build_scratch_model(tokenizer, ModelSettings(**TINY, attn_implementation=kernel), seed=0)
        assert model.config._attn_implementation == kernel
        losses[kernel] = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations, settings,
                                  tmp_path / kernel).final_loss
    assert losses["eager"] == pytest.approx(losses["sdpa"], rel=1e-4)


def test_bf16_autocast_trains_and_keeps_fp32_master_weights(tokenizer, conversations, tmp_path):
    repeated = conversations[:2] * 24
    settings = TrainSettings(max_steps=30, bf16=True, **QUIET)
    model = tiny_model(tokenizer)
    result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, repeated, settings, tmp_path)
    assert result.final_loss < 0.5 * math.log(len(tokenizer))
    assert next(model.parameters()).dtype == torch.float32  # master weights stay fp32


def test_packing_keeps_padding_small(tokenizer, conversations, tmp_path):
    def fraction(packing):
        # Width rounding off: these conversations are short, so rounding to 8 would dominate the padding.
        settings = TrainSettings(num_epochs=1, packing=packing, pad_to_multiple_of=1, **QUIET)
        out = tmp_path / str(packing)
        return finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, conversations, settings,
                        out).real_token_fraction

    packed, padded = fraction(True), fraction(False)
    assert packed >= 0.95 > padded


def test_the_heap_before_training_is_left_out_of_its_collections_and_handed_back(tokenizer, conversations, tmp_path):
    """accelerate's full collection at the training's start (and any during it) walks only what training made."""
    counts = []

    class Frozen(TrainerCallback):
        def on_train_begin(self, args, state, control, **kwargs):
            counts.append(gc.get_freeze_count())

    settings = TrainSettings(max_steps=2, **QUIET)
    finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, conversations, settings, tmp_path,
             callbacks=[Frozen()])
    assert counts and counts[0] > 10_000  # torch's and transformers' objects, among others
    assert gc.get_freeze_count() == 0


def test_saved_model_reloads_with_its_chat_format(tokenizer, conversations, tmp_path):
    model = tiny_model(tokenizer)
    result = finetune(model, tokenizer, WORD_LEVEL_FORMAT, conversations[:8],
                      TrainSettings(max_steps=2, **QUIET), tmp_path)
    loaded = load_model(result.model_dir)
    # The Trainer trains on the GPU when there is one; load_model loads on the CPU.
    assert all(torch.equal(a.cpu(), b) for a, b in zip(model.state_dict().values(), loaded.state_dict().values()))
    assert load_chat_format(result.model_dir) == WORD_LEVEL_FORMAT


class StopAt(TrainerCallback):
    """Simulates an interruption: training stops after ``step`` (its checkpoint is written first)."""

    def __init__(self, step):
        self.step = step

    def on_step_end(self, args, state, control, **kwargs):
        if state.global_step == self.step:
            control.should_training_stop = True


@pytest.mark.parametrize("optimizer, stretch, parts", [("adamw", 1.0, 1), ("muon", 1.0, 1), ("muon", 2.0, 1),
                                                        ("muon", 2.0, 2)])
def test_resume_after_interruption_matches_an_uninterrupted_run(tokenizer, conversations, tmp_path, optimizer, stretch,
                                                                parts):
    """Bit for bit: Trainer restores optimizer, schedule and RNG states, and the sampler (and the stretched
    positions' draws) come from torch's RNG."""
    settings = TrainSettings(max_steps=8, optimizer=optimizer, position_stretch=stretch, batch_threads=parts,
                             **{**QUIET, "save_steps": 3, "torch_threads": parts})  # parts need a thread each
    whole = finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, conversations, settings, tmp_path / "a")
    cut = finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, conversations, settings, tmp_path / "b",
                   callbacks=[StopAt(4)])
    assert cut.global_step == 4 and cut.checkpoint_steps == [3]
    resumed = finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, conversations, settings,
                       tmp_path / "b")
    assert resumed.resumed_from.endswith("checkpoint-3")
    assert resumed.global_step == whole.global_step == 8
    assert resumed.tokens_trained == whole.tokens_trained
    assert resumed.final_loss == whole.final_loss
    a, b = load_model(whole.model_dir), load_model(resumed.model_dir)
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), name


def test_metrics_land_in_the_active_mlflow_run(tokenizer, conversations, tmp_path):
    previous = mlflow.get_tracking_uri()
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path}/mlflow.db")
    try:
        experiment = mlflow.create_experiment("finetune", artifact_location=(tmp_path / "artifacts").as_uri())
        settings = TrainSettings(max_steps=4, eval_fraction=0.25, **{**QUIET, "report_to": ("mlflow",)})
        with mlflow.start_run(experiment_id=experiment) as run:
            result = finetune(tiny_model(tokenizer), tokenizer, WORD_LEVEL_FORMAT, conversations[:16], settings,
                              tmp_path / "out")
            assert mlflow.active_run().info.run_id == run.info.run_id  # the callback leaves our run open
        mlflow.flush_async_logging()
        client = mlflow.MlflowClient()
        assert [m.step for m in client.get_metric_history(run.info.run_id, "loss")] == [1, 2, 3, 4]
        assert 0.0 <= result.token_accuracy <= 1.0  # the held-out accuracy comes back (the finetune step logs it)
        assert client.get_run(run.info.run_id).data.params["lr_scheduler_type"] == "cosine"
    finally:
        mlflow.set_tracking_uri(previous)


def test_main_runs_a_request(tokenizer, conversations, tmp_path):
    tokenizer.save_pretrained(tmp_path / "tokenizer")
    data = tmp_path / "train.jsonl"
    data.write_text("".join(json.dumps({"conversations": turns}) + "\n" for turns in conversations[:8]))
    request = TrainRequest(model=ModelSettings(**TINY), train=TrainSettings(**{**QUIET, "max_steps": 2, "report_to": []}),
                           seed=0, data=str(data), tokenizer_dir=str(tmp_path / "tokenizer"),
                           output_dir=str(tmp_path / "run"))
    main(["--request", str(request.save(tmp_path / "request.json"))])
    result = json.loads((tmp_path / "run" / RESULT_FILE).read_text())
    assert result["global_step"] == 2
    assert load_model(result["model_dir"]).config.hidden_size == 32


def test_the_papers_gpu_settings_reach_the_trainer(tmp_path):
    args = _training_arguments(TrainSettings(gradient_checkpointing=True, tf32=True, **QUIET), tmp_path, 0)
    assert getattr(args, "activation_checkpointing", None) or args.gradient_checkpointing
    assert args.tf32 is (True if torch.cuda.is_available() else None)  # tf32 is a GPU setting: left alone on a CPU


def test_the_compilers_checks_run_ahead_in_a_thread_that_compiling_waits_for(monkeypatch, tokenizer):
    import time

    import torch._inductor.cpu_vec_isa as isa

    from pipeline.lm.training import compile as compile_module

    ran = []

    def slow_checks():
        time.sleep(0.3)
        ran.append((threading.current_thread().name, time.perf_counter()))

    monkeypatch.setattr(isa, "pick_vec_isa", slow_checks)
    monkeypatch.setattr(compile_module, "_warming", None)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    compile_module.warm_compiler()
    compile_module.warm_compiler()  # once per process
    model = build_scratch_model(tokenizer, ModelSettings(hidden_size=32, num_layers=2, num_heads=2,
                                                         intermediate_size=64), seed=0)
    with compile_module.compiled_blocks(model, "regional"):
        entered = time.perf_counter()
    assert [name for name, _ in ran] == ["inductor-isa-checks"]
    assert entered >= ran[0][1]  # compiling began only after the checks


def test_muon_precision_is_off_without_muon_or_bf16():
    assert TrainSettings(optimizer="muon", bf16=True, muon_bf16=True).muon_bf16
    assert not TrainSettings(optimizer="adamw", bf16=True, muon_bf16=True).muon_bf16
    assert not TrainSettings(optimizer="muon", bf16=False, muon_bf16=True).muon_bf16


@pytest.mark.parametrize("parts", [1, 2, 3])  # on the calling thread; on part threads (the norms shared out)
@pytest.mark.parametrize("scale", [1e-3, 10.0, float("nan")])  # below max_grad_norm, above it, and a nan gradient
def test_gradient_clipping_is_accelerates_bit_for_bit(scale, parts):
    """The trainer skips multiplying by a clip coefficient of exactly 1; otherwise it clips as accelerate does
    (whose total norm is the norm of the gradients' total norm, which can differ from torch's in the last bit),
    also with the tensors' norms and the clipping shared out among the part threads."""
    from types import SimpleNamespace

    from accelerate import Accelerator

    from pipeline.lm.training.trainer import _Trainer

    def model(seed):
        net = torch.nn.Sequential(torch.nn.Linear(8, 16), torch.nn.Linear(16, 4), torch.nn.Linear(4, 300))
        generator = torch.Generator().manual_seed(seed)
        for p in net.parameters():
            p.grad = torch.randn(p.shape, generator=generator) * scale
        return net

    ours, theirs = model(0), model(0)
    accelerator = Accelerator(cpu=True)
    threads = PartThreads(parts) if parts > 1 else None
    trainer = SimpleNamespace(accelerator=accelerator, args=SimpleNamespace(max_grad_norm=1.0, device=torch.device("cpu")),
                              _has_mixed_mesh_grads=lambda m: False, _trained=None, part_threads=threads)
    try:
        norm = _Trainer._clip_grad_norm(trainer, ours)
    finally:
        if threads is not None:
            threads.close()
    expected = accelerator.clip_grad_norm_(theirs.parameters(), 1.0)
    torch.testing.assert_close(norm, expected, rtol=0, atol=0, equal_nan=True)
    for a, b in zip(ours.parameters(), theirs.parameters()):
        torch.testing.assert_close(a.grad, b.grad, rtol=0, atol=0, equal_nan=True)


def test_token_accuracy_shared_out_among_threads_counts_what_one_thread_counts(tokenizer, conversations):
    """The held-out accuracy with its batches shared out among part threads: the same counts, odd shares included."""
    from pipeline.lm.training import trainer as trainer_module

    data = tokenize_conversations(tokenizer, WORD_LEVEL_FORMAT, conversations[:37], 512)
    model = tiny_model(tokenizer)
    seen = []
    original = trainer_module.head_at_labels

    def head(model, inputs):  # which threads computed batches; every third target made the argmax
        seen.append(threading.current_thread().name)
        logits, targets = original(model, inputs)
        rows = torch.arange(0, len(targets), 3)
        return logits.index_put((rows, targets[rows]), torch.tensor(100.0), accumulate=True), targets

    trainer_module.head_at_labels = head
    try:
        alone = trainer_module.token_accuracy(model, data, tokenizer.pad_token_id, batch_size=4)
        assert set(seen) == {threading.current_thread().name}
        seen.clear()
        shared = [trainer_module.token_accuracy(model, data, tokenizer.pad_token_id, batch_size=4, parts=parts)
                  for parts in (2, 3)]
    finally:
        trainer_module.head_at_labels = original
    assert alone is not None and 0.3 < alone < 1  # a third and what the untrained model gets right
    assert shared == [alone, alone]
    assert len(seen) == 2 * 10 and threading.current_thread().name not in seen  # 37 rows: 10 batches each time


def test_the_real_token_count_is_trainers_own():
    """On one process the trainer counts the real tokens seen without Trainer's gather: the same sum."""
    from types import SimpleNamespace

    from accelerate import Accelerator

    from pipeline.lm.training.trainer import _Trainer

    mask = torch.tensor([[1, 1, 1, 0], [1, 1, 0, 0]])
    inputs = {"input_ids": torch.zeros(2, 4, dtype=torch.long), "attention_mask": mask}

    def trainer(cls):
        made = object.__new__(cls)  # the attributes the count reads, without building a Trainer
        made.args = SimpleNamespace(include_num_input_tokens_seen="non_padding", device=torch.device("cpu"))
        made.accelerator, made.processing_class = Accelerator(cpu=True), None
        made.state, made.model = SimpleNamespace(num_input_tokens_seen=7), SimpleNamespace(main_input_name="input_ids")
        return made

    ours, theirs = trainer(_Trainer), trainer(Trainer)
    _Trainer._track_num_input_tokens(ours, inputs)
    Trainer._track_num_input_tokens(theirs, inputs)
    assert ours.state.num_input_tokens_seen == theirs.state.num_input_tokens_seen == 12
    ours.model.main_input_name = "inputs_embeds"  # not among the inputs: Trainer counts nothing (and warns)
    _Trainer._track_num_input_tokens(ours, inputs)
    assert ours.state.num_input_tokens_seen == 12
