"""A teacher-forced probe: fed the golden answer, does the model predict each label of the map?

Where `pipeline.core.map_errors.first_wrong_line` sees only the first wrong line of what a model wrote, the
probe grades every label line of the golden map (one forward pass a world), so a failure rate can be read by
what the neighbour is (free, visited, wall, pit, outside the grid).
"""

from __future__ import annotations

from typing import Sequence

import torch
from transformers import PreTrainedModel, PreTrainedTokenizerBase

from pipeline.lm.chat import ChatFormat, encode_prompt


@torch.no_grad()
def labels_predicted(model: PreTrainedModel, tokenizer: PreTrainedTokenizerBase, fmt: ChatFormat,
                     prompt: Sequence[dict], answer: str, lines: Sequence[int]) -> list[bool]:
    """For each of ``lines`` (0-based line indices of ``answer``), whether the model, prompted with ``prompt``
    and fed ``answer`` up to that line, predicts every token of the line (greedy). The answer is encoded as
    training encodes a gpt turn (its own piece after the gpt prefix), so the ids are the ones trained on."""
    context = encode_prompt(tokenizer, fmt, prompt)
    encoded = tokenizer(answer, add_special_tokens=False, return_offsets_mapping=True)
    ids, offsets = encoded["input_ids"], encoded["offset_mapping"]
    full = torch.tensor([context + ids], device=model.device)
    predicted = model(input_ids=full).logits[0, len(context) - 1: -1].argmax(-1).tolist()
    texts, starts = answer.split("\n"), [0]
    for text in texts[:-1]:
        starts.append(starts[-1] + len(text) + 1)
    graded = []
    for line in lines:
        begin, end = starts[line], starts[line] + len(texts[line])
        tokens = [i for i, (a, b) in enumerate(offsets) if a < end and b > begin]
        graded.append(bool(tokens) and all(predicted[i] == ids[i] for i in tokens))
    return graded
