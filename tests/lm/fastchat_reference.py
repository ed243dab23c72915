"""What the paper's training code (kaistAI/language_extrapolation, ``fastchat/train/train.py`` and the "llama-3"
template of ``fastchat/conversation.py``) makes of one conversation, written out here as the reference the
project's encoding is tested against.

That code renders the conversation to one string, tokenizes the string at once (the tokenizer putting
``<|begin_of_text|>`` first and cutting at the context length), and finds the targets by counting tokens:
each exchange (up to an ``<|end_of_text|><|begin_of_text|>``) is cut at its ``[/INST]\\n``; what comes before
the cut is masked, the answer and the two tokens after it are targets; the first token and everything after
the last exchange are masked. A sequence that was not cut short and whose count disagrees with its length is
masked whole. Beside it, the project's side of the comparison: its paper template and conversations of every
variant to encode.
"""

from __future__ import annotations

from typing import Sequence

from omegaconf import OmegaConf

from conftest import ROOT
from pipeline.core.generators import GeneratorConfig, generate_worlds
from pipeline.core.texts import conversation
from pipeline.core.variants import BY_NAME, DIRECTIONS, MODES, VARIANTS
from pipeline.lm.chat import IGNORE_INDEX, ChatFormat

HUMAN, GPT = "[INST]", "[/INST]\n"          # the template's two roles
GPT_END = "<|end_of_text|><|begin_of_text|>"  # what closes an answer (a human turn has no closing text)


def render_conversation(fmt: ChatFormat, turns: Sequence[dict], generation_prompt: bool = False) -> str:
    """A conversation as one text, written from the format's fields alone: each turn's prefix, value and end,
    ``bos`` once (with ``generation_prompt``, the gpt prefix after it). The encoder's ids must be this text's."""
    text = fmt.bos + "".join(fmt.prefix(turn["from"], index == 0) + turn["value"] + fmt.end(turn["from"])
                             for index, turn in enumerate(turns))
    return text + (fmt.gpt_prefix if generation_prompt else "")


def fastchat_prompt(turns: Sequence[dict]) -> str:
    """The template's string: ``[INST] `` and the first message, then each message after its role's tag,
    an answer followed by ``GPT_END``."""
    text = "[INST] " + turns[0]["value"]
    for index, turn in enumerate(turns[1:], 1):
        text += (GPT + turn["value"] + GPT_END) if index % 2 else (HUMAN + turn["value"])
    return text


def fastchat_ids_and_labels(tokenizer, turns: Sequence[dict], max_length: int) -> tuple[list[int], list[int]]:
    """Input ids and labels of one conversation as the paper's ``preprocess`` computes them (without the
    padding to ``max_length`` that it appends: the collator's business)."""
    prompt = fastchat_prompt(turns)
    ids = tokenizer(prompt, truncation=True, max_length=max_length).input_ids

    def count(text: str) -> int:  # tokens of a text, the BOS the tokenizer adds left out
        return len(tokenizer(text).input_ids) - 1

    masked, position = [(0, 1)], 1
    for exchange in prompt.split(GPT_END):
        halves = exchange.split(GPT)
        if not exchange or len(halves) != 2:
            break
        masked.append((position, position + count(halves[0] + GPT)))
        position += count(exchange) + 2
    masked.append((position, len(ids)))
    labels = list(ids)
    for start, stop in masked:
        labels[start:stop] = [IGNORE_INDEX] * len(labels[start:stop])
    if position < max_length and position != len(ids):
        labels = [IGNORE_INDEX] * len(ids)  # "tokenization mismatch": the paper's code trains nothing on it
    return ids, labels


# ------------------------------------------------------------------------- the project's side of the comparison
def paper_format() -> ChatFormat:
    """The project's paper template (``model/chat_format=paper``, the llama3_8b default)."""
    return ChatFormat(**OmegaConf.to_container(OmegaConf.load(ROOT / "conf/model/chat_format/paper.yaml")))


def paper_conversations(n_worlds: int = 3, prompts=("paper", "task"), sizes=(2, 6)) -> list[list[dict]]:
    """Every defined (variant, direction, mode, prompt) on a few worlds of ``sizes`` cells a side."""
    worlds = generate_worlds(n_worlds, seed="llama3-template", cfg=GeneratorConfig(size_x=sizes, size_y=sizes, frame=20))
    return [conversation(world, direction, variant, mode, prompt=prompt)
            for world in worlds for variant in VARIANTS for direction in DIRECTIONS for mode in MODES
            for prompt in prompts if mode == "reachable" or not BY_NAME[variant].reachable_only]
