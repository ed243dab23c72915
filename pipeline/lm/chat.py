"""Turning ShareGPT conversations into token ids: the one place training and decoding agree on.

A conversation renders as ``[bos] + (prefix(role) + value + end(role))*`` and is encoded in pieces: each run
of context (the BOS, a human turn with its prefix and end, and the gpt prefix after it) as one text, then
each gpt value and its ``turn_end`` on their own. A context run is encoded whole because a subword tokenizer
merges across its joins: Llama-3's encodes ``[INST] You`` as ``[``, ``INST``, ``]``, `` You``, where the prefix
encoded apart gives `` ``, ``You`` (the paper's code tokenizes the whole rendered string at once). The pieces
end where a decoder's input does (after the gpt prefix; after a turn end), so the ids of a prefix of the
conversation are exactly a prefix of the ids of the whole: a decoder appends the next observation to a cached
sequence without re-encoding the history. Loss targets are the gpt values (less the spans a turn lists as
`UNTRAINED`) and their ``turn_end`` token(s).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Protocol, Sequence

IGNORE_INDEX = -100
# A gpt turn's optional key: the [start, end) character spans of its value that are no loss targets (encoded
# as pieces of their own, cut at the spans' ends).
UNTRAINED = "untrained"


class TextTokenizer(Protocol):
    """What we need of a tokenizer: transformers' fast tokenizers satisfy it."""

    def encode(self, text: str, add_special_tokens: bool = ...) -> list[int]: ...

    def decode(self, ids: Sequence[int], skip_special_tokens: bool = ...) -> str: ...


@dataclass
class ChatFormat:
    """Role markers around each turn. ``bos`` is prepended once (empty: none). ``turn_end`` ends a gpt turn,
    and a human turn too unless ``human_end`` says otherwise; ``first_human_prefix`` (when set) opens the
    first human turn instead of ``human_prefix``. A decoder stops a gpt turn at ``stop`` (default: the whole
    ``turn_end``), and closes it with the rest of ``turn_end`` before the next human turn."""

    human_prefix: str = "<human>"
    gpt_prefix: str = "<gpt>"
    turn_end: str = "</s>"
    bos: str = "<s>"
    first_human_prefix: Optional[str] = None
    human_end: Optional[str] = None
    stop: Optional[str] = None

    def prefix(self, role: str, first: bool = False) -> str:
        if role == "human":
            return self.first_human_prefix if first and self.first_human_prefix is not None else self.human_prefix
        if role == "gpt":
            return self.gpt_prefix
        raise ValueError(f"unknown turn role {role!r}; allowed: 'human', 'gpt'")

    def end(self, role: str) -> str:
        return self.human_end if role == "human" and self.human_end is not None else self.turn_end


# The word-level tokenizer's format; paper-scale models name their own in the model config.
WORD_LEVEL_FORMAT = ChatFormat()


def _encode(tokenizer: TextTokenizer, text: str) -> list[int]:
    return tokenizer.encode(text, add_special_tokens=False) if text else []


def _context(fmt: ChatFormat, turn: dict, first: bool) -> str:
    """A non-gpt turn's text: its prefix, value and end."""
    return fmt.prefix(turn["from"], first) + turn["value"] + fmt.end(turn["from"])


def _pieces(fmt: ChatFormat, turns: Sequence[dict], generation_prompt: bool) -> list[tuple[str, bool]]:
    """The conversation's text as it is encoded: (text, is a loss target) pieces, context runs whole."""
    pieces, context = [], fmt.bos
    for index, turn in enumerate(turns):
        if turn["from"] != "gpt":
            context += _context(fmt, turn, index == 0)
            continue
        pieces += [(context + fmt.gpt_prefix, False), *_value_pieces(turn), (fmt.turn_end, True)]
        context = ""
    return pieces + [(context + (fmt.gpt_prefix if generation_prompt else ""), False)]


def _value_pieces(turn: dict) -> list[tuple[str, bool]]:
    """A gpt value as (text, is a loss target) pieces: whole, or cut around its `UNTRAINED` spans."""
    value, pieces, at = turn["value"], [], 0
    for start, end in sorted(turn.get(UNTRAINED, ())):
        if not at <= start <= end <= len(value):
            raise ValueError(f"{UNTRAINED} span [{start}, {end}) of a gpt turn: expected spans in order, without "
                             f"overlap, within its value of {len(value)} characters")
        pieces += [(value[at:start], True), (value[start:end], False)]
        at = end
    return [piece for piece in pieces + [(value[at:], True)] if piece[0]] or [(value, True)]


# Pieces a Rust tokenizer encodes in one call: large enough that the call's own cost vanishes, small enough
# that the Encoding objects of one call stay a few megabytes.
_BATCH = 4096


def plain_backend(tokenizer: TextTokenizer):
    """The Rust tokenizer behind a transformers fast tokenizer whose ``encode`` is the backend's alone (its class
    overrides no encoding method), set as ``encode`` sets it before each call: no padding, no truncation (an
    earlier call, or the tokenizer's file, may have left either on the backend) and special tokens split as the
    tokenizer says. None for any other tokenizer."""
    backend = getattr(tokenizer, "backend_tokenizer", None)
    if backend is None:
        return None
    from transformers.tokenization_utils_tokenizers import TokenizersBackend

    cls = type(tokenizer)
    if not isinstance(tokenizer, TokenizersBackend) or any(
            getattr(cls, name) is not getattr(TokenizersBackend, name) for name in ("encode", "_encode_plus")):
        return None
    if backend.truncation is not None:
        backend.no_truncation()
    if backend.padding is not None:
        backend.no_padding()
    backend.encode_special_tokens = bool(getattr(tokenizer, "split_special_tokens", False))
    return backend


def _encode_all(tokenizer: TextTokenizer, texts: Sequence[str]) -> list[list[int]]:
    """`_encode` of each text. A transformers fast tokenizer (`plain_backend`) has its Rust backend encode them
    in batches, in parallel and without a Python call a text: the ids ``encode`` returns."""
    backend = plain_backend(tokenizer)
    if backend is None:
        return [_encode(tokenizer, text) for text in texts]
    nonempty = [text for text in texts if text]
    ids = []
    for start in range(0, len(nonempty), _BATCH):
        ids += [encoding.ids for encoding in backend.encode_batch(nonempty[start:start + _BATCH],
                                                                  add_special_tokens=False)]
    encoded = iter(ids)
    return [next(encoded) if text else [] for text in texts]


def encode_conversation(
    tokenizer: TextTokenizer, fmt: ChatFormat, turns: Sequence[dict]
) -> tuple[list[int], list[int]]:
    """Token ids of a whole conversation and labels with loss on gpt turns only: targets on each gpt value
    and its whole turn end (as the paper's FastChat fork trains: the ``<|end_of_text|><|begin_of_text|>`` after
    an answer is a target there too)."""
    return encode_conversations(tokenizer, fmt, [turns])[0]


def encode_conversations(
    tokenizer: TextTokenizer, fmt: ChatFormat, conversations: Sequence[Sequence[dict]],
    encode_texts: Callable[[Sequence[str]], list[list[int]]] | None = None,
) -> list[tuple[list[int], list[int]]]:
    """`encode_conversation` of each conversation, their pieces encoded together: by ``encode_texts`` when given
    (it must give `_encode`'s ids: `pipeline.lm.tokenizer.word_level_encoder`), else `_encode_all` (the CPU
    default's 49,000 training conversations took 13.3 s one piece at a time on a 2-core EPYC, 6.8 s in batches)."""
    pieces = [_pieces(fmt, turns, generation_prompt=False) for turns in conversations]
    texts = [text for conversation in pieces for text, _ in conversation]
    encoded = iter(encode_texts(texts) if encode_texts is not None else _encode_all(tokenizer, texts))
    result = []
    for conversation in pieces:
        ids, labels = [], []
        for _, target in conversation:
            piece = next(encoded)
            ids += piece
            labels += piece if target else [IGNORE_INDEX] * len(piece)
        result.append((ids, labels))
    return result


def encode_prompt(tokenizer: TextTokenizer, fmt: ChatFormat, turns: Sequence[dict]) -> list[int]:
    """Ids of the turns so far followed by the gpt prefix: what a model continues from."""
    return [i for text, _ in _pieces(fmt, turns, generation_prompt=True) for i in _encode(tokenizer, text)]


def encode_followup(tokenizer: TextTokenizer, fmt: ChatFormat, human_value: str) -> list[int]:
    """Ids to append after a finished gpt turn (ending in ``turn_end``): the next human turn and gpt prefix."""
    return _encode(tokenizer, _context(fmt, {"from": "human", "value": human_value}, False) + fmt.gpt_prefix)


def turn_end_ids(tokenizer: TextTokenizer, fmt: ChatFormat) -> list[int]:
    """The ids that end a gpt turn (what closes an answer cut at its cap)."""
    return _encode(tokenizer, fmt.turn_end)


def stop_ids(tokenizer: TextTokenizer, fmt: ChatFormat) -> list[int]:
    """The ids a decoder stops a gpt turn at: the start of `turn_end_ids` (all of it unless ``fmt.stop``)."""
    end = turn_end_ids(tokenizer, fmt)
    if fmt.stop is None:
        return end
    stop = _encode(tokenizer, fmt.stop)
    if not stop or end[:len(stop)] != stop:
        raise ValueError(f"chat format stop={fmt.stop!r} must encode to the first ids of turn_end={fmt.turn_end!r}")
    return stop


def read_conversations(path: str | Path) -> list[list[dict]]:
    """Conversations from JSONL, in order: each line a list of turns or an object with a ``conversations`` list."""
    conversations = []
    with open(path) as lines:
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            record = json.loads(line)
            turns = record["conversations"] if isinstance(record, dict) else record
            if not isinstance(turns, list):
                raise ValueError(f"{path}:{number}: expected a list of turns or {{'conversations': [...]}}")
            conversations.append(turns)
    return conversations
