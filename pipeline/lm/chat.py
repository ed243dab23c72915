"""Turning ShareGPT conversations into token ids: the one place training and decoding agree on.

A conversation is encoded turn by turn: ``[bos] + (prefix(role) + value + turn_end)*``. Each piece is
encoded on its own, so the ids of a prefix of the conversation are exactly a prefix of the ids of the whole:
a decoder can append the next observation to a cached sequence without re-encoding the history.
Loss targets are the gpt values and their ``turn_end`` token(s); everything else is context.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence

IGNORE_INDEX = -100


class TextTokenizer(Protocol):
    """What we need of a tokenizer: transformers' fast tokenizers satisfy it."""

    def encode(self, text: str, add_special_tokens: bool = ...) -> list[int]: ...

    def decode(self, ids: Sequence[int], skip_special_tokens: bool = ...) -> str: ...


@dataclass(frozen=True)
class ChatFormat:
    """Role markers around each turn. ``bos`` is prepended once (empty: none)."""

    human_prefix: str = "<human>"
    gpt_prefix: str = "<gpt>"
    turn_end: str = "</s>"
    bos: str = "<s>"

    def prefix(self, role: str) -> str:
        if role == "human":
            return self.human_prefix
        if role == "gpt":
            return self.gpt_prefix
        raise ValueError(f"unknown turn role {role!r}; allowed: 'human', 'gpt'")


# The word-level tokenizer's format; paper-scale models name their own in the model config.
WORD_LEVEL_FORMAT = ChatFormat()


def _encode(tokenizer: TextTokenizer, text: str) -> list[int]:
    return tokenizer.encode(text, add_special_tokens=False) if text else []


def encode_turn(tokenizer: TextTokenizer, fmt: ChatFormat, role: str, value: str) -> tuple[list[int], list[int]]:
    """Ids of one turn and its labels (targets only on a gpt turn's value and end marker)."""
    prefix = _encode(tokenizer, fmt.prefix(role))
    body = _encode(tokenizer, value) + _encode(tokenizer, fmt.turn_end)
    labels = [IGNORE_INDEX] * len(prefix) + (body if role == "gpt" else [IGNORE_INDEX] * len(body))
    return prefix + body, labels


def encode_conversation(
    tokenizer: TextTokenizer, fmt: ChatFormat, turns: Sequence[dict]
) -> tuple[list[int], list[int]]:
    """Token ids of a whole conversation and labels with loss on gpt turns only."""
    ids = _encode(tokenizer, fmt.bos)
    labels = [IGNORE_INDEX] * len(ids)
    for turn in turns:
        turn_ids, turn_labels = encode_turn(tokenizer, fmt, turn["from"], turn["value"])
        ids += turn_ids
        labels += turn_labels
    return ids, labels


def encode_prompt(tokenizer: TextTokenizer, fmt: ChatFormat, turns: Sequence[dict]) -> list[int]:
    """Ids of the turns so far followed by the gpt prefix: what a model continues from."""
    ids, _ = encode_conversation(tokenizer, fmt, turns)
    return ids + _encode(tokenizer, fmt.gpt_prefix)


def encode_followup(tokenizer: TextTokenizer, fmt: ChatFormat, human_value: str) -> list[int]:
    """Ids to append after a finished gpt turn (ending in ``turn_end``): the next human turn and gpt prefix."""
    ids, _ = encode_turn(tokenizer, fmt, "human", human_value)
    return ids + _encode(tokenizer, fmt.gpt_prefix)


def turn_end_ids(tokenizer: TextTokenizer, fmt: ChatFormat) -> list[int]:
    """The ids that end a turn; a decoder stops a sequence when it has produced them."""
    return _encode(tokenizer, fmt.turn_end)
