"""A word-level tokenizer built for Gridworld text (the CPU-default model's vocabulary).

A coordinate ``(x, y)`` is one piece (one word of this language: the model matches a cell against the
obstacle lists by token identity instead of assembling five pieces, and sequences are about half as long);
other pieces are numbers (or their digits: `NUMBER_PIECES`), words and punctuation, each optionally with one
leading space, plus single whitespace characters. Decoding concatenates pieces, so
``decode(encode(text)) == text`` for any text in the vocabulary. The vocabulary is the sorted set of pieces of the training texts plus every coordinate the
frame can produce (``-1`` .. ``frame`` on both axes), so extrapolated test worlds never meet an unknown cell.
"""

from __future__ import annotations

import re
from functools import lru_cache
from typing import Iterable

from tokenizers import Regex, Tokenizer, decoders, models, pre_tokenizers
from transformers import PreTrainedTokenizerFast

from pipeline.lm.chat import WORD_LEVEL_FORMAT
from pipeline.lm.model_settings import NUMBERS

# How a number outside a cell is cut (`ModelSettings.numbers`): one piece a number, with its leading space
# (`whole`: "Step 12" is "Step", " 12"), or one piece a digit, the space its own piece (`digits`: "Step", " ",
# "1", "2"), so a larger number than training shows is made of pieces that training does show.
NUMBER_PIECES = {"whole": r" ?-?\d+", "digits": r"\d"}
assert tuple(NUMBER_PIECES) == NUMBERS


def piece_pattern(numbers: str = "whole") -> str:
    """The pieces' regex. "(" never takes a leading space, so " (1, 1)" is a space and the same cell word as at
    a line start."""
    return rf"\(-?\d+, -?\d+\)|{NUMBER_PIECES[numbers]}| ?[A-Za-z']+|\n| ?[^\sA-Za-z\d(]|\(|\s"


UNK, PAD = "<unk>", "<pad>"
SPECIAL_TOKENS = (PAD, UNK, WORD_LEVEL_FORMAT.bos, WORD_LEVEL_FORMAT.turn_end,
                  WORD_LEVEL_FORMAT.human_prefix, WORD_LEVEL_FORMAT.gpt_prefix)


@lru_cache(maxsize=len(NUMBERS))
def _pre_tokenizer(numbers: str = "whole") -> pre_tokenizers.PreTokenizer:
    return pre_tokenizers.Split(Regex(piece_pattern(numbers)), behavior="isolated")


def pieces(text: str, numbers: str = "whole") -> list[str]:
    """The pieces a text splits into (each becomes one token)."""
    return [piece for piece, _ in _pre_tokenizer(numbers).pre_tokenize_str(text)]


_PIECE_RES = {numbers: re.compile(piece_pattern(numbers)) for numbers in NUMBERS}


@lru_cache(maxsize=1024)
def piece_set(text: str, numbers: str = "whole") -> frozenset[str]:
    """The distinct pieces of ``text`` (the words a word-level model must have trained to read or write it)."""
    return frozenset(_PIECE_RES[numbers].findall(text))


# Cached: the instruction turn, the longest, repeats in every conversation.
@lru_cache(maxsize=1024)
def count_pieces(text: str, numbers: str = "whole") -> int:
    """How many tokens ``text`` becomes (the tokenizer's own pattern, without building an Encoding)."""
    return len(_PIECE_RES[numbers].findall(text))


def coverage_text(frame: int) -> str:
    """Every cell and every number a coordinate can take in a frame (numbers with and without a space)."""
    numbers = range(-1, frame + 1)
    cells = "".join(f"({x}, {y})" for x in numbers for y in numbers)
    return cells + " " + " ".join(str(n) for n in numbers) + " " + ",".join(str(n) for n in numbers)


def build_word_tokenizer(texts: Iterable[str], frame: int = 20, numbers: str = "whole") -> PreTrainedTokenizerFast:
    """A deterministic word-level tokenizer whose vocabulary covers ``texts`` and all frame coordinates;
    ``numbers``: how it cuts a number (`NUMBER_PIECES`)."""
    if numbers not in NUMBERS:
        raise ValueError(f"numbers={numbers!r}; allowed: {', '.join(NUMBERS)}")
    vocab_pieces: set[str] = set()
    splitter = _pre_tokenizer(numbers)
    digits = "0123456789" if numbers == "digits" else ""   # every number is made of known pieces
    for text in [coverage_text(frame), digits, *texts]:
        vocab_pieces.update(piece for piece, _ in splitter.pre_tokenize_str(text))
    vocab = {token: i for i, token in enumerate(SPECIAL_TOKENS)}
    for piece in sorted(vocab_pieces - set(SPECIAL_TOKENS)):
        vocab[piece] = len(vocab)
    core = Tokenizer(models.WordLevel(vocab=vocab, unk_token=UNK))
    core.pre_tokenizer = splitter
    core.decoder = decoders.Fuse()
    core.add_special_tokens(list(SPECIAL_TOKENS))
    return PreTrainedTokenizerFast(
        tokenizer_object=core,
        bos_token=WORD_LEVEL_FORMAT.bos,
        eos_token=WORD_LEVEL_FORMAT.turn_end,
        pad_token=PAD,
        unk_token=UNK,
        additional_special_tokens=[WORD_LEVEL_FORMAT.human_prefix, WORD_LEVEL_FORMAT.gpt_prefix],
        clean_up_tokenization_spaces=False,
    )

