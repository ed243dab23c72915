"""A word-level tokenizer built for Gridworld text (the CPU-default model's vocabulary).

A coordinate ``(x, y)`` is one piece (one word of this language: the model matches a cell against the
obstacle lists by token identity instead of assembling five pieces, and sequences are about half as long);
other pieces are numbers (or their digits: `NUMBER_PIECES`), words and punctuation, each optionally with one
leading space, plus single whitespace characters. With newlines ``joined`` (`NEWLINE_PIECES`) a cell, word or
punctuation mark that ends a line carries its newline: the same text in about two thirds of the tokens. With
spaces ``phrases`` (`SPACE_PIECES`) each run of words, spaces and marks up to a cell, a digit, a line end or a full
stop is one piece instead.
Decoding concatenates pieces, so ``decode(encode(text)) == text`` for any text in the vocabulary. The vocabulary
is the sorted set of pieces of the training texts plus every coordinate the frame can produce (``-1`` ..
``frame`` on both axes, with newlines joined also ending a line), so extrapolated test worlds never meet an
unknown cell.
"""

from __future__ import annotations

import json
import re
from functools import lru_cache
from typing import Callable, Iterable, Sequence

from tokenizers import Regex, Tokenizer, decoders, models, pre_tokenizers
from transformers import PreTrainedTokenizerFast

from pipeline.lm.chat import WORD_LEVEL_FORMAT, plain_backend
from pipeline.lm.model_settings import NEWLINES, NUMBERS, SPACES

# How a number outside a cell is cut (`ModelSettings.numbers`): one piece a number, with its leading space
# (`whole`: "Step 12" is "Step", " 12"), or one piece a digit, the space its own piece (`digits`: "Step", " ",
# "1", "2"), so a larger number than training shows is made of pieces that training does show.
NUMBER_PIECES = {"whole": r" ?-?\d+", "digits": r"\d"}
assert tuple(NUMBER_PIECES) == NUMBERS
# Where a newline goes (`ModelSettings.newlines`): its own piece (`own`: "up", "\n"), or at the end of the cell,
# word or punctuation mark before it (`joined`: "up\n"; a cell then has two words, "(1, 2)" and "(1, 2)\n").
NEWLINE_PIECES = {"own": "", "joined": r"\n?", "composed": r"\n?"}
assert tuple(NEWLINE_PIECES) == NEWLINES
# Where a space before a cell goes (`ModelSettings.spaces`), and with `digits` a space before a digit too (a whole
# number keeps its own leading space): its own piece (`own`: "Step", " ", "1"), or at the end of the word or
# punctuation mark before it (`joined`: "Step ", "1"; " at ", "(2, 4)"; ": ", "(2, 5)\n"). The lookahead keeps
# every other space where it was (a word's own leading space).
# `phrases`: every run of words, spaces and marks up to a cell, a digit, a line end or a sentence's full stop is one
# piece ("Grid is from ", " to ", "There is no pit.", " The wall is at ", ", and ", "Thought:\n"): the fixed
# phrases of the format, each one token, and the sentences between them still apart, so any pits-and-walls line is
# made of trained pieces.
SPACE_PIECES = {"own": {}, "joined": {"whole": r" (?=\()", "digits": r" (?=[(\d])"}, "phrases": {}}
assert tuple(SPACE_PIECES) == SPACES
PHRASE = r"(?:[^\d(\n.]+\.?|\.)"


def piece_pattern(numbers: str = "whole", newlines: str = "own", spaces: str = "own") -> str:
    """The pieces' regex. "(" never takes a leading space, so " (1, 1)" is a space (or, with spaces ``joined``,
    the end of the word before it; with ``phrases``, the end of the phrase before it) and the same cell word as at a
    line start."""
    newline, space = NEWLINE_PIECES[newlines], SPACE_PIECES[spaces].get(numbers, "")
    if spaces == "phrases":
        return rf"\(-?\d+, -?\d+\){newline}|{NUMBER_PIECES[numbers]}|{PHRASE}{newline}|\n|\("
    end = newline if not space else f"(?:{newline[:-1]}|{space})?" if newline else f"(?:{space})?"
    return rf"\(-?\d+, -?\d+\){newline}|{NUMBER_PIECES[numbers]}| ?[A-Za-z']+{end}|\n| ?[^\sA-Za-z\d(]{end}|\(|\s"


UNK, PAD = "<unk>", "<pad>"
SPECIAL_TOKENS = (PAD, UNK, WORD_LEVEL_FORMAT.bos, WORD_LEVEL_FORMAT.turn_end,
                  WORD_LEVEL_FORMAT.human_prefix, WORD_LEVEL_FORMAT.gpt_prefix)


@lru_cache(maxsize=len(NUMBERS) * len(NEWLINES) * len(SPACES))
def _pre_tokenizer(numbers: str = "whole", newlines: str = "own", spaces: str = "own") -> pre_tokenizers.PreTokenizer:
    return pre_tokenizers.Split(Regex(piece_pattern(numbers, newlines, spaces)), behavior="isolated")


def pieces(text: str, numbers: str = "whole", newlines: str = "own", spaces: str = "own") -> list[str]:
    """The pieces a text splits into (each becomes one token)."""
    return [piece for piece, _ in _pre_tokenizer(numbers, newlines, spaces).pre_tokenize_str(text)]


_PIECE_RES = {(numbers, newlines, spaces): re.compile(piece_pattern(numbers, newlines, spaces))
              for numbers in NUMBERS for newlines in NEWLINES for spaces in SPACES}
# The same regexes by their pattern, as a saved tokenizer's pre-tokenizer names it (`word_level_encoder`).
_PATTERN_RES = {regex.pattern: regex for regex in _PIECE_RES.values()}


# Cached: the instruction turn, the longest, repeats in every conversation.
@lru_cache(maxsize=1024)
def piece_census(text: str, numbers: str = "whole", newlines: str = "own", spaces: str = "own"
                 ) -> tuple[int, frozenset[str]]:
    """How many tokens ``text`` becomes and which distinct pieces it holds, from one pass of the tokenizer's own
    pattern (no Encoding built)."""
    found = _PIECE_RES[numbers, newlines, spaces].findall(text)
    return len(found), frozenset(found)


def piece_set(text: str, numbers: str = "whole", newlines: str = "own", spaces: str = "own") -> frozenset[str]:
    """The distinct pieces of ``text`` (the words a word-level model must have trained to read or write it)."""
    return piece_census(text, numbers, newlines, spaces)[1]


def coverage_text(frame: int, newlines: str = "own", spaces: str = "own") -> str:
    """Every cell (with newlines joined, also ending a line) and every number a coordinate can take in a frame
    (numbers with and without a space); with newlines `composed`, also a newline alone (the row every joined
    word adds to its word's: `pipeline.lm.models.ComposedRows`), after a space, or with spaces `phrases` (where a
    space takes the newline after it) after a number."""
    numbers = range(-1, frame + 1)
    forms = ("", "\n") if newlines != "own" else ("",)
    cells = "".join(f"({x}, {y}){end}" for x in numbers for y in numbers for end in forms)
    newline = ("\n" if spaces == "phrases" else " \n") if newlines == "composed" else ""
    return cells + " " + " ".join(str(n) for n in numbers) + " " + ",".join(str(n) for n in numbers) + newline


# Printable ASCII, tabs and newlines: where Python's regex engine and the tokenizer's (Oniguruma) read the pattern's
# classes (\d, \s, letters) alike, so `re.findall` gives the pre-tokenizer's pieces (and no gaps between them).
_PLAIN = re.compile(r"[\x20-\x7e\t\n]*")


def _all_pieces(texts: Iterable[str], numbers: str, newlines: str, spaces: str) -> set[str]:
    """The distinct pieces of ``texts``: plain texts through Python's regex (the CPU default's 100,000 training
    texts: 0.6 s instead of 7 s through the pre-tokenizer), any other through the tokenizer's own pre-tokenizer."""
    regex, splitter, found = _PIECE_RES[numbers, newlines, spaces], _pre_tokenizer(numbers, newlines, spaces), set()
    for text in texts:
        if _PLAIN.fullmatch(text):
            found.update(regex.findall(text))
        else:
            found.update(piece for piece, _ in splitter.pre_tokenize_str(text))
    return found


def build_word_tokenizer(texts: Iterable[str], frame: int = 20, numbers: str = "whole",
                         newlines: str = "own", spaces: str = "own") -> PreTrainedTokenizerFast:
    """A deterministic word-level tokenizer whose vocabulary covers ``texts`` and all frame coordinates;
    ``numbers``: how it cuts a number (`NUMBER_PIECES`); ``newlines``: where a newline goes (`NEWLINE_PIECES`);
    ``spaces``: where a space before a cell (or digit) goes (`SPACE_PIECES`)."""
    if numbers not in NUMBERS:
        raise ValueError(f"numbers={numbers!r}; allowed: {', '.join(NUMBERS)}")
    if newlines not in NEWLINES:
        raise ValueError(f"newlines={newlines!r}; allowed: {', '.join(NEWLINES)}")
    if spaces not in SPACES:
        raise ValueError(f"spaces={spaces!r}; allowed: {', '.join(SPACES)}")
    digits = "0123456789" if numbers == "digits" else ""   # every number is made of known pieces
    vocab_pieces = _all_pieces({coverage_text(frame, newlines, spaces), digits, *texts}, numbers, newlines, spaces)
    vocab = {token: i for i, token in enumerate(SPECIAL_TOKENS)}
    for piece in sorted(vocab_pieces - set(SPECIAL_TOKENS)):
        vocab[piece] = len(vocab)
    core = Tokenizer(models.WordLevel(vocab=vocab, unk_token=UNK))
    core.pre_tokenizer = _pre_tokenizer(numbers, newlines, spaces)
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


def word_level_encoder(tokenizer) -> Callable[[Sequence[str]], list[list[int]]] | None:
    """For a tokenizer this module built (or its saved copy), a function that gives each text's
    ``tokenizer.encode(text, add_special_tokens=False)`` ids: a plain text (`_PLAIN`) through Python's regex and
    the vocabulary (each added token's string its own id, as the tokenizer matches them before pre-tokenizing;
    any other piece its word's id, or ``<unk>``'s), any other text through the tokenizer itself. The CPU default's
    200,000 training texts: 1.6 s against 3.9 s through the Rust backend on two threads, the same ids (README,
    Speed). None for any other tokenizer: its saved state must show no normalizer, one of this module's piece
    patterns split ``isolated``, a word-level model, added tokens that match as they are written, and special
    tokens not split (`chat.plain_backend`: encoding not overridden)."""
    backend = plain_backend(tokenizer)
    if backend is None or backend.encode_special_tokens or not isinstance(backend.model, models.WordLevel):
        return None  # before reading the whole state: a subword tokenizer's is megabytes
    state = json.loads(backend.to_str())
    split, model, added = state.get("pre_tokenizer") or {}, state.get("model") or {}, state.get("added_tokens") or []
    regex = _PATTERN_RES.get((split.get("pattern") or {}).get("Regex"))
    if (state.get("normalizer") is not None or split.get("type") != "Split" or split.get("behavior") != "Isolated"
            or split.get("invert") or regex is None or model.get("type") != "WordLevel" or not added
            or any(token.get(flag) for token in added for flag in ("lstrip", "rstrip", "single_word", "normalized"))):
        return None
    vocab, unk = model["vocab"], model["vocab"].get(model.get("unk_token"))
    if unk is None:
        return None
    ids = {token["content"]: token["id"] for token in added}
    # Longest first, as the tokenizer matches added tokens; the group keeps them in `split`'s output.
    specials = re.compile("(" + "|".join(map(re.escape, sorted(ids, key=len, reverse=True))) + ")")

    def encode(text: str) -> list[int]:
        if not _PLAIN.fullmatch(text):
            return tokenizer.encode(text, add_special_tokens=False) if text else []
        out: list[int] = []
        for index, segment in enumerate(specials.split(text)):
            if index % 2:
                out.append(ids[segment])
            elif segment:
                out += [vocab.get(piece, unk) for piece in regex.findall(segment)]
        return out

    return lambda texts: [encode(text) for text in texts]
