"""The paper's chat template (model/chat_format=paper, the llama3_8b default): the exact rendered string, the
token-level loss mask, and decoding's stop and close ids, with a tokenizer built here that knows the
Llama-3 special tokens, and with the real Llama-3 tokenizer against the ids the paper's code produces."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf
from tokenizers import Tokenizer, decoders, models, pre_tokenizers
from transformers import PreTrainedTokenizerFast

from conftest import ROOT
from fastchat_reference import paper_conversations, paper_format, render_conversation
from pipeline.lm.chat import (
    IGNORE_INDEX, UNTRAINED, ChatFormat, encode_conversation, encode_conversations, encode_followup, encode_prompt,
    stop_ids, turn_end_ids,
)

SPECIAL = ("<|begin_of_text|>", "<|end_of_text|>", "[INST]", "[/INST]")
TURNS = [{"from": "human", "value": "Rules here."}, {"from": "gpt", "value": "OK"},
         {"from": "human", "value": "Grid is here."}, {"from": "gpt", "value": "Plan:\nup"}]


@pytest.fixture(scope="module")
def tokenizer() -> PreTrainedTokenizerFast:
    """Byte-level pieces (one token per character) plus the Llama-3 specials as single tokens."""
    vocab = {token: i for i, token in enumerate(SPECIAL)}
    for code in range(256):
        vocab.setdefault(chr(code), len(vocab))
    core = Tokenizer(models.WordLevel(vocab=vocab, unk_token="[INST]"))
    core.pre_tokenizer = pre_tokenizers.Split(pattern="", behavior="isolated")
    core.decoder = decoders.Fuse()
    core.add_special_tokens(list(SPECIAL))
    return PreTrainedTokenizerFast(tokenizer_object=core, bos_token=SPECIAL[0], eos_token=SPECIAL[1],
                                   pad_token=SPECIAL[1], clean_up_tokenization_spaces=False)


def test_the_paper_template_renders_the_fastchat_llama3_string():
    expected = ("<|begin_of_text|>[INST] Rules here.[/INST]\nOK<|end_of_text|><|begin_of_text|>"
                "[INST]Grid is here.[/INST]\nPlan:\nup<|end_of_text|><|begin_of_text|>")
    assert render_conversation(paper_format(), TURNS) == expected
    assert render_conversation(paper_format(), TURNS[:3], generation_prompt=True).endswith("Grid is here.[/INST]\n")


def test_ids_are_the_rendered_text_and_the_loss_covers_gpt_texts_and_their_ends_only(tokenizer):
    fmt = paper_format()
    ids, labels = encode_conversation(tokenizer, fmt, TURNS)
    assert tokenizer.decode(ids) == render_conversation(fmt, TURNS)
    targets = [(i, token) for i, (token, label) in enumerate(zip(ids, labels)) if label != IGNORE_INDEX]
    assert all(labels[i] == token for i, token in targets)
    assert tokenizer.decode([token for _, token in targets]) == (
        "OK<|end_of_text|><|begin_of_text|>Plan:\nup<|end_of_text|><|begin_of_text|>")
    # Nothing of the human turns, the [INST]/[/INST] markers or the first BOS is a target.
    first_gpt = tokenizer.decode(ids[: targets[0][0]])
    assert first_gpt == "<|begin_of_text|>[INST] Rules here.[/INST]\n"


class _OneByOne:
    """A tokenizer with ``encode`` alone (no Rust backend to batch with)."""

    def __init__(self, tokenizer):
        self.tokenizer = tokenizer

    def encode(self, text, add_special_tokens=True):
        return self.tokenizer.encode(text, add_special_tokens=add_special_tokens)


def test_conversations_encoded_together_are_each_encoded_alone(tokenizer):
    fmt = paper_format()
    conversations = [TURNS, TURNS[:2], [*TURNS[:3], {**TURNS[3], UNTRAINED: [[0, 1]]}],
                     [{"from": "human", "value": ""}]]
    together = encode_conversations(tokenizer, fmt, conversations)
    assert together == encode_conversations(_OneByOne(tokenizer), fmt, conversations)
    assert together == [encode_conversation(_OneByOne(tokenizer), fmt, turns) for turns in conversations]
    assert tokenizer.decode(together[0][0]) == render_conversation(fmt, TURNS)
    # What an earlier call left on the Rust backend (padding, truncation) does not reach the batches.
    tokenizer(["a", "a b c"], padding=True, truncation=True, max_length=2)
    assert encode_conversations(tokenizer, fmt, conversations) == together


def test_untrained_spans_of_a_gpt_turn_keep_its_ids_and_drop_their_targets(tokenizer):
    fmt = paper_format()
    marked = [*TURNS[:3], {**TURNS[3], UNTRAINED: [[5, 6], [0, 1]]}]   # "P" and "\n" of "Plan:\nup"
    ids, labels = encode_conversation(tokenizer, fmt, marked)
    whole, whole_labels = encode_conversation(tokenizer, fmt, TURNS)
    assert ids == whole
    dropped = [i for i, (a, b) in enumerate(zip(labels, whole_labels)) if a != b]
    assert [tokenizer.decode([whole[i]]) for i in dropped] == ["P", "\n"]
    assert all(labels[i] == IGNORE_INDEX for i in dropped)
    for bad in ([[3, 2]], [[0, 4], [2, 6]], [[0, 99]]):
        with pytest.raises(ValueError, match="untrained span"):
            encode_conversation(tokenizer, fmt, [*TURNS[:3], {**TURNS[3], UNTRAINED: bad}])


def test_decoding_stops_at_end_of_text_and_closes_the_turn_before_the_next_observation(tokenizer):
    fmt = paper_format()
    end, eot, bot = turn_end_ids(tokenizer, fmt), tokenizer.convert_tokens_to_ids(SPECIAL[1]), tokenizer.convert_tokens_to_ids(SPECIAL[0])
    assert end == [eot, bot] and stop_ids(tokenizer, fmt) == [eot]
    prompt = encode_prompt(tokenizer, fmt, TURNS[:3])
    assert tokenizer.decode(prompt).endswith("[INST]Grid is here.[/INST]\n")
    # A finished answer stops at <|end_of_text|>; the rest of the turn end opens the next human turn.
    followup = end[1:] + encode_followup(tokenizer, fmt, "Current:\n(0, 1)")
    whole, _ = encode_conversation(tokenizer, fmt, [*TURNS, {"from": "human", "value": "Current:\n(0, 1)"}])
    assert prompt + tokenizer.encode("Plan:\nup", add_special_tokens=False) + [eot] + followup == \
        whole + tokenizer.encode("[/INST]\n", add_special_tokens=False)


def test_a_stop_that_is_not_the_start_of_the_turn_end_is_refused(tokenizer):
    with pytest.raises(ValueError, match="stop='\\[INST\\]' must encode to the first ids"):
        stop_ids(tokenizer, ChatFormat(turn_end="<|end_of_text|>", stop="[INST]"))


def test_llama3_8b_defaults_to_the_paper_template_and_keeps_the_instruct_headers_as_an_option():
    from conftest import compose_job

    paper = compose_job(ROOT / "outputs", "model=llama3_8b").model.chat_format
    instruct = compose_job(ROOT / "outputs", "model=llama3_8b", "model/chat_format=llama3_instruct").model.chat_format
    assert ChatFormat(**OmegaConf.to_container(paper)) == paper_format()
    assert instruct.turn_end == "<|eot_id|>" and instruct.first_human_prefix is None


# ------------------------------------------------------------------ the real Llama-3 tokenizer (tests/fixtures)
def test_the_fixture_is_meta_llama3s_tokenizer(llama3_tokenizer):
    # The ids of Meta's own tokenizer test (meta-llama/llama3, llama/test_tokenizer.py).
    assert llama3_tokenizer("This is a test sentence.").input_ids == [128000, 2028, 374, 264, 1296, 11914, 13]
    assert len(llama3_tokenizer) == 128256
    assert (llama3_tokenizer.bos_token, llama3_tokenizer.eos_token) == ("<|begin_of_text|>", "<|end_of_text|>")
    assert llama3_tokenizer.pad_token is None  # as Meta ships it: the trainer must add one


def test_the_paper_template_gives_the_papers_ids_and_loss_mask_with_the_real_tokenizer(llama3_tokenizer):
    from fastchat_reference import fastchat_ids_and_labels

    fmt = paper_format()
    conversations = paper_conversations()
    assert len(conversations) == 3 * 2 * (2 * 2 * 14 + 2)  # 14 variants in both modes, DFS reachable only
    for turns, (ids, labels) in zip(conversations, encode_conversations(llama3_tokenizer, fmt, conversations)):
        assert (ids, labels) == fastchat_ids_and_labels(llama3_tokenizer, turns, max_length=8192)
        # ... and they are the rendered string tokenized at once, as the paper's code does.
        assert ids == llama3_tokenizer(render_conversation(fmt, turns), add_special_tokens=False).input_ids


def test_the_first_human_turn_is_encoded_with_its_prefix(llama3_tokenizer):
    # Encoded apart, "[INST] " ended in a lone space and the instruction began "You" (issue 24: every
    # conversation of every variant differed from the paper's ids by that one split).
    fmt = paper_format()
    (turns,) = paper_conversations(1, prompts=("paper",))[:1]
    ids, labels = encode_conversation(llama3_tokenizer, fmt, turns)
    assert llama3_tokenizer.convert_ids_to_tokens(ids[:6]) == ["<|begin_of_text|>", "[", "INST", "]", "ĠYou", "Ġare"]
    assert ids[:6] == [128000, 58, 65562, 60, 1472, 527]
    apart = llama3_tokenizer.encode("[INST] ", add_special_tokens=False) + llama3_tokenizer.encode("You are", add_special_tokens=False)
    assert llama3_tokenizer.convert_ids_to_tokens(apart) == ["[", "INST", "]", "Ġ", "You", "Ġare"]
    assert set(labels[:6]) == {IGNORE_INDEX}


def test_cached_decoding_appends_exactly_the_ids_training_sees_with_the_real_tokenizer(llama3_tokenizer):
    # The decoder's sequence (prompt, answer, stop, rest of the turn end, next observation and gpt prefix,
    # ...) must be the training conversation's ids, so a cached episode sees what training showed.
    fmt = paper_format()
    end = turn_end_ids(llama3_tokenizer, fmt)
    stop = stop_ids(llama3_tokenizer, fmt)
    reachable = [t for t in paper_conversations(2, prompts=("paper", "task")) if len(t) > 4]
    assert reachable
    for turns in reachable:
        first = 3 if turns[1]["from"] == "gpt" else 1  # the paper's three prompt turns, or the task alone
        sequence = encode_prompt(llama3_tokenizer, fmt, turns[:first])
        for index in range(first, len(turns), 2):
            sequence += llama3_tokenizer.encode(turns[index]["value"], add_special_tokens=False) + stop
            if index + 1 < len(turns):
                sequence += end[len(stop):] + encode_followup(llama3_tokenizer, fmt, turns[index + 1]["value"])
        whole, _ = encode_conversation(llama3_tokenizer, fmt, turns)
        assert sequence + end[len(stop):] == whole
