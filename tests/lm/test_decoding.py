"""Decoding: batched == unbatched, cached turns == re-encoded history, per-item errors, rows leave the batch."""

from __future__ import annotations

import importlib.util

import pytest
import torch
from transformers import LlamaConfig, LlamaForCausalLM

from pipeline.lm.chat import WORD_LEVEL_FORMAT, encode_prompt, turn_end_ids
from pipeline.lm.decoding.hf import HFDecoder
from pipeline.core.environment import Outcome
from pipeline.core.generators import GeneratorConfig, generate_worlds
from pipeline.core.scoring import parse_action
from pipeline.core.texts import conversation, prompt_turns
from pipeline.lm.tokenizer import build_word_tokenizer

FMT = WORD_LEVEL_FORMAT


@pytest.fixture(scope="module")
def worlds():
    return generate_worlds(6, seed="decode-tests", cfg=GeneratorConfig(size_x=(2, 4), size_y=(2, 4)))


@pytest.fixture(scope="module")
def tokenizer(worlds):
    texts = [turn["value"] for world in worlds for turn in conversation(world, "fwd", "marking-deadend", "reachable")]
    return build_word_tokenizer(texts)


@pytest.fixture(scope="module")
def model(tokenizer):
    torch.manual_seed(0)
    # A large init spread makes the random model's greedy outputs varied rather than one repeated token.
    config = LlamaConfig(vocab_size=len(tokenizer), hidden_size=32, num_hidden_layers=2, num_attention_heads=4,
                         num_key_value_heads=2, intermediate_size=64, max_position_embeddings=2048,
                         initializer_range=0.5)
    return LlamaForCausalLM(config).eval()


class StopAtPositions(torch.nn.Module):
    """The random model, forced to end its turn whenever the next position is a multiple of `period`.

    Position-based, so the cached and the re-encoded runs are forced alike, and answers end at different
    lengths across rows (rows leave the batch at different steps).
    """

    def __init__(self, inner, stop_id: int, period: int):
        super().__init__()
        self.inner, self.stop_id, self.period = inner, stop_id, period

    @property
    def config(self):
        return self.inner.config

    @property
    def device(self):
        return self.inner.device

    def forward(self, position_ids, **kwargs):
        out = self.inner(position_ids=position_ids, **kwargs)
        forced = (position_ids[:, -1] + 1) % self.period == 0
        out.logits[forced, -1, self.stop_id] = 1e4
        return out


@pytest.fixture(scope="module")
def stopping_model(model, tokenizer):
    return StopAtPositions(model, turn_end_ids(tokenizer, FMT)[0], period=7)


def random_walk(text: str, observation: str) -> str | None:
    """Stand-in policy: a free move picked by the answer text, so random models play many turns."""
    lines = observation.split("Possible:\n")[-1].split("\n")
    moves = lines[1::2]
    return moves[sum(map(ord, text)) % len(moves)] if moves else None


def count_rows_per_forward(model):
    """Hook that records (batch rows, width) of every forward call."""
    calls = []
    handle = model.register_forward_pre_hook(lambda _m, _a, kw: calls.append(tuple(kw["input_ids"].shape)),
                                             with_kwargs=True)
    return calls, handle


def test_batched_answers_equal_unbatched_and_generate_in_input_order(model, tokenizer, worlds):
    prompts = [prompt_turns(world) for world in reversed(worlds)]
    batched = HFDecoder(model, tokenizer, FMT, batch_size=3, max_new_tokens=16).generate(prompts)
    single = HFDecoder(model, tokenizer, FMT, batch_size=1, max_new_tokens=16).generate(prompts)
    assert [g.text for g in batched] == [g.text for g in single]
    assert len({g.text for g in batched}) > 1, "the random model should answer prompts differently"
    stop = turn_end_ids(tokenizer, FMT)[0]
    for turns, gen in zip(prompts, batched):
        ids = torch.tensor([encode_prompt(tokenizer, FMT, turns)])
        out = model.generate(ids, attention_mask=torch.ones_like(ids), do_sample=False, max_new_tokens=16,
                             eos_token_id=stop, pad_token_id=0)[0, ids.shape[1]:].tolist()
        expected = out[:-1] if out[-1] == stop else out
        assert gen.text == tokenizer.decode(expected, skip_special_tokens=False)
        assert gen.n_tokens == len(out) and gen.finished == (out[-1] == stop)


def test_answers_stop_at_turn_end_and_stopped_rows_cost_nothing(stopping_model, tokenizer, worlds):
    prompts = [prompt_turns(world) for world in worlds]
    calls, handle = count_rows_per_forward(stopping_model)
    try:
        gens = HFDecoder(stopping_model, tokenizer, FMT, batch_size=4, max_new_tokens=50).generate(prompts)
    finally:
        handle.remove()
    assert all(g.finished and g.stop_reason == "turn_end" and g.error is None for g in gens)
    assert all(1 <= g.n_tokens <= 7 and FMT.turn_end not in g.text for g in gens)  # turn end counted
    assert len({g.n_tokens for g in gens}) > 1
    # Each decode step feeds one token per row still going: the last token of an answer is never fed.
    assert sum(rows for rows, width in calls if width == 1) == sum(g.n_tokens - 1 for g in gens)


def test_context_overflow_gives_per_item_errors(model, tokenizer, worlds):
    prompts = [prompt_turns(world) for world in worlds]
    lengths = sorted(len(encode_prompt(tokenizer, FMT, turns)) for turns in prompts)
    assert lengths[0] < lengths[-1]
    limit = lengths[-1]  # the longest prompts do not fit (a prompt needs room for one token), the rest do
    gens = HFDecoder(model, tokenizer, FMT, batch_size=4, max_new_tokens=50, max_length=limit).generate(prompts)
    for turns, gen in zip(prompts, gens):
        n = len(encode_prompt(tokenizer, FMT, turns))
        if n >= limit:
            assert gen.error and gen.stop_reason == "error" and gen.text == ""
        else:
            assert gen.error is None
            assert gen.finished or n + gen.n_tokens == limit  # truncated exactly at the context's end
    assert any(g.error for g in gens) and any(g.error is None for g in gens)


@pytest.mark.parametrize("baseline", ["reencode", "generate"])
def test_cached_turns_equal_reencoded_history(model, tokenizer, worlds, baseline):
    decoder = HFDecoder(model, tokenizer, FMT, batch_size=3, max_new_tokens=8, max_followup_tokens=3)
    cached = decoder.play(worlds, max_moves=6, choose_move=random_walk)
    reference = decoder.play(worlds, max_moves=6, choose_move=random_walk, strategy=baseline)
    assert [r.answers for r in cached] == [r.answers for r in reference]
    assert [(r.outcome, r.moves) for r in cached] == [(r.outcome, r.moves) for r in reference]
    assert sum(r.n_moves for r in cached) > 2 * len(worlds), "episodes should run several turns"


def test_cached_turns_equal_reencoded_when_rows_stop_at_different_steps(stopping_model, tokenizer, worlds):
    decoder = HFDecoder(stopping_model, tokenizer, FMT, batch_size=4, max_new_tokens=20, max_followup_tokens=20)
    cached = decoder.play(worlds, max_moves=6, choose_move=random_walk)
    reencoded = decoder.play(worlds, max_moves=6, choose_move=random_walk, strategy="reencode")
    assert [r.answers for r in cached] == [r.answers for r in reencoded]
    assert len({len(a) for r in cached for a in r.answers}) > 2


def test_finished_episodes_leave_the_batch(stopping_model, tokenizer, worlds):
    finished = []
    calls, handle = count_rows_per_forward(stopping_model)
    try:
        decoder = HFDecoder(stopping_model, tokenizer, FMT, batch_size=3, max_new_tokens=20, max_followup_tokens=20)
        results = decoder.play(worlds, max_moves=5, choose_move=random_walk, on_episode=finished.append)
    finally:
        handle.remove()
    assert [r.world_index for r in results] == list(range(len(worlds)))
    assert sorted(r.world_index for r in finished) == list(range(len(worlds)))
    assert sorted(finished, key=lambda r: r.world_index) == results
    n_answers = sum(len(r.answers) for r in results)
    assert sum(rows for rows, width in calls if width == 1) == sum(r.n_tokens for r in results) - n_answers
    # Prefill/extension calls carry only live episodes: one row per answer, over all calls.
    assert sum(rows for rows, width in calls if width > 1) == n_answers
    assert max(rows for rows, _ in calls) <= 3


def test_garbage_answers_end_episodes_as_invalid(model, tokenizer, worlds):
    results = HFDecoder(model, tokenizer, FMT, batch_size=4, max_new_tokens=16).play(worlds)
    for result in results:
        assert result.error is None and result.outcome is not None
        if parse_action(result.answers[-1]) is None:
            assert result.outcome == Outcome.INVALID
    assert any(r.outcome == Outcome.INVALID for r in results)
    assert [r.world_index for r in results] == list(range(len(worlds)))


def test_context_overflow_ends_episodes_with_an_error(model, tokenizer, worlds):
    lengths = [len(encode_prompt(tokenizer, FMT, prompt_turns(world))) for world in worlds]
    limit = sorted(lengths)[len(lengths) // 2] + 40
    decoder = HFDecoder(model, tokenizer, FMT, batch_size=3, max_new_tokens=8, max_followup_tokens=4,
                        max_length=limit)
    results = decoder.play(worlds, max_moves=50, choose_move=random_walk)
    for n, result in zip(lengths, results):
        if n >= limit:
            assert result.error and result.answers == [] and result.outcome is None
    grew_out = [r for n, r in zip(lengths, results) if n < limit and r.error]
    assert grew_out and all(r.n_moves > 0 and r.outcome is None for r in grew_out)


@pytest.mark.skipif(importlib.util.find_spec("vllm") is not None, reason="vLLM is installed")
def test_vllm_decoder_without_vllm_says_how_to_install(tokenizer):
    from pipeline.lm.decoding.vllm import VLLMDecoder

    with pytest.raises(ImportError, match=r"pip install '\.\[gpu\]'"):
        VLLMDecoder("some/model", tokenizer, FMT)


def test_vllm_refuses_a_model_whose_attention_it_does_not_run(tmp_path):
    from pipeline.lm.decoding import make_decoder

    (tmp_path / "config.json").write_text('{"model_type": "llama", "attention_scale": "log_length"}')
    with pytest.raises(ValueError, match="backend='vllm' cannot decode .*log_length.*expected backend='hf'"):
        make_decoder(str(tmp_path), backend="vllm")
