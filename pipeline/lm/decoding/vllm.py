"""Greedy decoding with vLLM: the same `answer` / `play` interface as `pipeline.lm.decoding.hf.HFDecoder`.

vLLM is the optional `[gpu]` extra, imported only when a `VLLMDecoder` is built. Prompts go in as token ids
(encoded by `pipeline.lm.chat`, exactly as in training). In the reachable setting each turn resubmits the
whole history; with `enable_prefix_caching=True` vLLM finds the history's KV blocks in its prefix cache,
so only the new observation and the answer are computed. The episode loop is `decode.play_episodes`.
"""

from __future__ import annotations

from typing import Callable, Sequence

from pipeline.lm.chat import ChatFormat, TextTokenizer, encode_prompt, stop_ids
from pipeline.lm.decoding.loop import (
    Continuation,
    DecodedEpisode,
    Generation,
    HistorySequences,
    MoveChooser,
    context_error,
    generation,
    play_episodes,
)
from pipeline.core.texts import DEFAULT_PROMPT
from pipeline.core.world import World


def _import_vllm():
    try:
        import vllm
    except ImportError as err:
        raise ImportError("VLLMDecoder needs vLLM, an optional dependency: pip install '.[gpu]'") from err
    return vllm


class VLLMDecoder:
    """Greedy decoding with `vllm.LLM`; `model` is a path/hub name or an `LLM` already built.

    An `LLM` passed in should have been built with `enable_prefix_caching=True`. `batch_size` is how many
    episodes play at once (vLLM batches their sequences itself). The turn end must be one token.
    """

    def __init__(
        self,
        model,
        tokenizer: TextTokenizer,
        fmt: ChatFormat,
        *,
        batch_size: int = 256,
        max_new_tokens: int = 4096,
        max_followup_tokens: int = 64,
        max_length: int | None = None,
        **llm_kwargs,
    ):
        vllm = _import_vllm()
        self.stop_ids = stop_ids(tokenizer, fmt)
        if len(self.stop_ids) != 1:
            raise ValueError(f"VLLMDecoder needs a one-token turn end; {fmt.turn_end!r} is {self.stop_ids}")
        if isinstance(model, str):
            llm_kwargs.setdefault("enable_prefix_caching", True)
            llm_kwargs.setdefault("max_model_len", max_length)
            model = vllm.LLM(model=model, **{k: v for k, v in llm_kwargs.items() if v is not None})
        self.llm, self._sampling_params = model, vllm.SamplingParams
        self.tokenizer, self.fmt = tokenizer, fmt
        self.batch_size, self.max_new_tokens, self.max_followup_tokens = batch_size, max_new_tokens, max_followup_tokens
        self.max_length = max_length or self.llm.llm_engine.model_config.max_model_len

    def generate(self, prompts: Sequence[Sequence[dict]], max_new_tokens: int | None = None) -> list[Generation]:
        """Greedy answers to conversations (each ending with a human turn), in input order."""
        cap = max_new_tokens or self.max_new_tokens
        encoded = [encode_prompt(self.tokenizer, self.fmt, turns) for turns in prompts]
        fitting = [i for i, ids in enumerate(encoded) if len(ids) < self.max_length]
        outs = dict(zip(fitting, self._continue_prompts([encoded[i] for i in fitting], [cap] * len(fitting))))
        return [
            generation(self.tokenizer, outs[i]) if i in outs
            else Generation("", 0, False, "error", context_error(len(ids), self.max_length))
            for i, ids in enumerate(encoded)
        ]

    def play(
        self,
        worlds: Sequence[World],
        *,
        max_moves: int = 200,
        on_episode: Callable[[DecodedEpisode], None] | None = None,
        choose_move: MoveChooser | None = None,
        prompt: str = DEFAULT_PROMPT,
        rules: str = "project",
    ) -> list[DecodedEpisode]:
        """Play every world's episode, `batch_size` at a time (see `decode.play_episodes`)."""
        backend = HistorySequences(self._continue_prompts, self.stop_ids, self.max_length)
        return play_episodes(
            backend, self.tokenizer, self.fmt, worlds, batch_size=self.batch_size, max_moves=max_moves,
            max_new_tokens=self.max_new_tokens, max_followup_tokens=self.max_followup_tokens,
            on_episode=on_episode, choose_move=choose_move, prompt=prompt, rules=rules,
        )

    def _continue_prompts(self, prompts: list[list[int]], caps: list[int]) -> list[Continuation]:
        """Whole token sequences (each shorter than max_length) continued greedily to the turn end."""
        if not prompts:
            return []
        params = [
            self._sampling_params(temperature=0.0, max_tokens=min(cap, self.max_length - len(prompt)),
                                  stop_token_ids=self.stop_ids, ignore_eos=True, detokenize=False)
            for prompt, cap in zip(prompts, caps)
        ]
        outputs = self.llm.generate([{"prompt_token_ids": p} for p in prompts], params, use_tqdm=False)
        results = []
        for prompt, cap, output in zip(prompts, caps, outputs):
            completion = output.outputs[0]
            ids = list(completion.token_ids)
            if completion.finish_reason == "stop":
                # Whether vLLM keeps the stop token in token_ids has varied across versions.
                results.append(Continuation(ids[:-1] if ids[-1:] == self.stop_ids else ids, "turn_end", n_stop=1))
            else:
                full = len(prompt) + len(ids) >= self.max_length
                results.append(Continuation(ids, "context" if full and len(ids) < cap else "max_new_tokens"))
        return results
