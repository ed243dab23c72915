"""The teacher-forced probe grades exactly the tokens of each asked line, against the model's greedy choice."""

from types import SimpleNamespace

import torch

from pipeline.core.map_errors import label_kinds
from pipeline.core.texts import golden_answer, prompt_turns
from pipeline.core.world import World
from pipeline.lm.chat import WORD_LEVEL_FORMAT, encode_prompt
from pipeline.lm.probe import labels_predicted
from pipeline.lm.tokenizer import build_word_tokenizer

WORLD = World(3, 3, 0, 0, ((1, 1),), ((0, 2),), (0, 0), (2, 2))
ANSWER = golden_answer(WORLD, "bwd", "marking-deadend", "optimal")
PROMPT = prompt_turns(WORLD, "task")
TOKENIZER = build_word_tokenizer([t["value"] for t in PROMPT] + [ANSWER], frame=4)


class Oracle(torch.nn.Module):
    """Predicts the golden answer's next token everywhere, except the tokens it is told to get wrong."""

    def __init__(self, ids: list[int], wrong: set[int]):
        super().__init__()
        self.ids, self.wrong, self.device = ids, wrong, torch.device("cpu")

    def forward(self, input_ids):
        assert input_ids[0].tolist() == self.ids
        logits = torch.zeros(1, len(self.ids), len(TOKENIZER))
        for position, token in enumerate(self.ids[1:]):
            logits[0, position, (token + 1) % len(TOKENIZER) if position + 1 in self.wrong else token] = 1.0
        return SimpleNamespace(logits=logits)


def test_each_line_is_graded_on_its_own_tokens():
    context = encode_prompt(TOKENIZER, WORD_LEVEL_FORMAT, PROMPT)
    ids = context + TOKENIZER.encode(ANSWER, add_special_tokens=False)
    lines = [line for line, _ in label_kinds(WORLD, "bwd", "marking-deadend")]
    assert labels_predicted(Oracle(ids, set()), TOKENIZER, WORD_LEVEL_FORMAT, PROMPT, ANSWER, lines) == \
        [True] * len(lines)
    # Get the second label's token wrong (one word a line here): only that line fails.
    texts = ANSWER.split("\n")
    position = len(context) + len(TOKENIZER.encode("\n".join(texts[: lines[1]]) + "\n", add_special_tokens=False))
    assert TOKENIZER.decode([ids[position]]) == texts[lines[1]]
    graded = labels_predicted(Oracle(ids, {position}), TOKENIZER, WORD_LEVEL_FORMAT, PROMPT, ANSWER, lines)
    assert graded == [index != 1 for index in range(len(lines))]
