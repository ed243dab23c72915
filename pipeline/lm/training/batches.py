"""Training batches: tokenized conversations, the right-padding collator and length-grouped batches.

With packing (the default) batches are grouped by length and right-padded *without* an attention mask.
Causal attention never looks right, so the padding cannot reach a real token and each sequence computes
exactly what it would alone, while SDPA keeps its fast ``is_causal`` kernel; grouping keeps the padding to a
few percent. Flattening a batch into one row (``DataCollatorWithFlattening``) is exact in transformers 5 only
when no KV cache is created (``use_cache=False``, which Trainer sets), and on a CPU its block-diagonal mask
costs attention over the whole row (benchmarks/bench_train.py measures both).
"""

from __future__ import annotations

import logging
import math
import random
from dataclasses import dataclass
from typing import Sequence

import torch
from transformers import PreTrainedTokenizerBase

from pipeline.lm.chat import IGNORE_INDEX, ChatFormat, encode_conversations
from pipeline.lm.tokenizer import word_level_encoder
from pipeline.lm.training.settings import LONG_CONVERSATIONS

log = logging.getLogger(__name__)


class ConversationDataset(torch.utils.data.Dataset):
    """Tokenized conversations (``input_ids``, ``labels``); of those over ``max_length``, ``dropped`` counts
    the ones left out and ``truncated`` the ones cut to it."""

    def __init__(self, examples: list[dict[str, list[int]]], dropped: int = 0, truncated: int = 0):
        self.examples = examples
        self.dropped = dropped
        self.truncated = truncated

    def __len__(self) -> int:
        return len(self.examples)

    def __getitem__(self, index: int) -> dict[str, list[int]]:
        return self.examples[index]

    @property
    def lengths(self) -> list[int]:
        return [len(example["input_ids"]) for example in self.examples]


def tokenize_conversations(
    tokenizer: PreTrainedTokenizerBase, fmt: ChatFormat, conversations: Sequence[Sequence[dict]], max_length: int,
    long_conversations: str = "drop", part: str = "training",
) -> ConversationDataset:
    """Encode conversations with loss on gpt turns only. One longer than ``max_length`` tokens is dropped
    (``long_conversations="drop"``) or cut to its first ``max_length`` tokens and trained on the targets left
    (``"truncate"``, as the paper's code does); one cut before its first target is dropped. Which happened,
    and to how many, is logged as one line naming the ``part``."""
    if long_conversations not in LONG_CONVERSATIONS:
        raise ValueError(f"long_conversations={long_conversations!r}; allowed: {', '.join(LONG_CONVERSATIONS)}")
    examples, dropped, truncated = [], 0, 0
    for input_ids, labels in encode_conversations(tokenizer, fmt, conversations, word_level_encoder(tokenizer)):
        if len(input_ids) > max_length:
            input_ids, labels = input_ids[:max_length], labels[:max_length]
            if long_conversations == "drop" or all(label == IGNORE_INDEX for label in labels):
                dropped += 1
                continue
            truncated += 1
        examples.append({"input_ids": input_ids, "labels": labels})
    if dropped or truncated:
        what = (f"{truncated} truncated to their first {max_length} tokens, {dropped} dropped (no target left)"
                if long_conversations == "truncate" else "dropped")
        log.warning("%s: %d of %d conversations are longer than max_length=%d tokens (train.long_conversations=%s): "
                    "%s", part, dropped + truncated, len(conversations), max_length, long_conversations, what)
    return ConversationDataset(examples, dropped, truncated)


def stretched_positions(n: int, stretch: float, generator: torch.Generator | None = None) -> torch.Tensor:
    """Position ids for a sequence of ``n`` tokens as if it were longer: a random ordered subset of ``n`` of
    the first ``round(n * s)`` positions, ``s`` drawn uniformly from [1, ``stretch``] (Ruoss et al. 2023's
    randomized positions, with the range scaled to the sequence). At ``s`` = 1 it is 0 .. n - 1, the positions
    decoding uses, so inference stays in the training distribution; larger ``s`` trains the distances between
    tokens that longer (larger-world) conversations put between them."""
    s = 1 + (stretch - 1) * torch.rand((), generator=generator).item()
    span = max(n, round(n * s))
    return torch.randperm(span, generator=generator)[:n].sort().values


def stretched_batch_positions(attention_mask: torch.Tensor, stretch: float, seed: int) -> torch.Tensor:
    """`stretched_positions` for each row of a right-padded batch (its real tokens: ``attention_mask``), the
    padding numbered on after the last real token; drawn from a generator seeded with ``seed`` alone, so the
    same batch and seed give the same positions whatever ran before (a resumed run draws what the uninterrupted
    one drew; accelerate's data loader collates a batch ahead of the step, so torch's global generator cannot)."""
    generator = torch.Generator().manual_seed(seed)
    counts = attention_mask.sum(dim=1).cpu()  # built on the CPU, moved to the mask's device at the end
    width = attention_mask.shape[1]
    if width == 0:
        return torch.zeros(attention_mask.shape, dtype=torch.long, device=attention_mask.device)
    drawn = [stretched_positions(n, stretch, generator) for n in counts.tolist() if n]  # the rows' draws, in order
    # Real tokens lead each row (right padding), so the rows' draws concatenated fill the mask's ones in order.
    columns = torch.arange(width)
    real = columns < counts[:, None]
    positions = torch.zeros(len(counts), width, dtype=torch.long)
    if drawn:
        positions[real] = torch.cat(drawn)
    # The padding numbered on after the row's last position (a row with no real token: 0, 1, ...).
    last = positions.gather(1, (counts - 1).clamp(min=0)[:, None])
    after = torch.where(counts[:, None] > 0, last + 1 + columns - counts[:, None], columns)
    return torch.where(real, positions, after).to(attention_mask.device)


@dataclass
class RightPadCollator:
    """Pads to the longest sequence on the right. With ``attention_mask=False`` (packing) no mask is sent:
    causal attention keeps every real token blind to the padding after it, and SDPA uses ``is_causal``.
    Stretched positions (`stretched_batch_positions`, added by the trainer per step) need the mask: without
    one, transformers reads a jump in the position ids as the start of another packed sequence."""

    pad_token_id: int
    attention_mask: bool = False
    pad_to_multiple_of: int = 1

    def __post_init__(self) -> None:
        if not isinstance(self.pad_token_id, int) or self.pad_token_id < 0:
            raise ValueError(f"pad_token_id={self.pad_token_id!r}: expected a token id (an integer >= 0); a "
                             "tokenizer without a pad token gets one from pipeline.lm.models.with_pad_token")

    def __call__(self, features: list[dict]) -> dict[str, torch.Tensor]:
        lengths = [len(f["input_ids"]) for f in features]
        width = -(-max(lengths) // self.pad_to_multiple_of) * self.pad_to_multiple_of
        # Each tensor from one padded list of lists: one call instead of one a row (a step's batch is built on the
        # training loop's thread, between steps).
        pad = self.pad_token_id
        input_ids = torch.tensor([[*f["input_ids"], *[pad] * (width - n)] for f, n in zip(features, lengths)],
                                 dtype=torch.long)
        labels = torch.tensor([[*f["labels"], *[IGNORE_INDEX] * (width - n)] for f, n in zip(features, lengths)],
                              dtype=torch.long)
        batch = {"input_ids": input_ids, "labels": labels}
        if self.attention_mask:
            batch["attention_mask"] = (torch.arange(width) < torch.tensor(lengths)[:, None]).long()
        return batch


class LengthGroupedBatches(torch.utils.data.Sampler[int]):
    """Indices whose consecutive ``batch_size`` runs are batches of similar length, in random batch order.

    Each epoch: a random permutation, cut into megabatches of ``megabatch_mult`` batches, each sorted by length
    and cut into batches; then the full batches are shuffled and the one short batch (the last megabatch's
    remainder, if the data set is not a multiple of ``batch_size``) goes last. The data loader cuts this order
    into runs of ``batch_size`` again, so a short batch in the middle would shift every later run across two
    length groups (it did: 8% of the computed tokens were padding on the default job, against about 2%).
    transformers' LengthGroupedSampler shrinks megabatches to a quarter of a small data set (8% padding on a few
    hundred conversations) and runs each megabatch from the longest batch to the shortest, a length curriculum we
    do not want. Randomness comes from torch's global generator, which Trainer seeds and restores on resume.
    """

    def __init__(self, lengths: Sequence[int], batch_size: int, megabatch_mult: int = 50):
        self.lengths, self.batch_size, self.megabatch_mult = list(lengths), batch_size, megabatch_mult

    def __len__(self) -> int:
        return len(self.lengths)

    def __iter__(self):
        order = torch.randperm(len(self.lengths)).tolist()
        size = self.batch_size * self.megabatch_mult
        batches = []
        for start in range(0, len(order), size):
            megabatch = sorted(order[start:start + size], key=self.lengths.__getitem__)
            batches += [megabatch[i:i + self.batch_size] for i in range(0, len(megabatch), self.batch_size)]
        short = [batches.pop()] if batches and len(batches[-1]) < self.batch_size else []
        shuffled = [i for b in torch.randperm(len(batches)).tolist() for i in batches[b]]
        return iter(shuffled + [i for b in short for i in b])


def split_eval(conversations: Sequence, fraction: float, seed: int) -> tuple[list, list]:
    """A seeded (train, eval) split holding out ``fraction`` of the conversations."""
    order = list(range(len(conversations)))
    random.Random(seed).shuffle(order)
    n_eval = math.floor(len(order) * fraction)
    held = set(order[:n_eval])
    train = [c for i, c in enumerate(conversations) if i not in held]
    return train, [conversations[i] for i in sorted(held)]

