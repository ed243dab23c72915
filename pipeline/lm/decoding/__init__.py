"""Greedy decoding: the backend-independent episode loop (`loop`), the transformers backend (`hf`) and vLLM
(`vllm`); `make_decoder` opens a finetuned model directory with the backend asked for."""

from __future__ import annotations

from typing import Protocol

from pipeline.core.texts import DEFAULT_PROMPT
from pipeline.core.world import World

BACKENDS = ("hf", "vllm")


class Decoder(Protocol):
    """What evaluation needs of a decoding backend (`hf.HFDecoder`, `vllm.VLLMDecoder`)."""

    def generate(self, prompts: list[list[dict]]) -> list: ...

    def play(self, worlds: list[World], *, max_moves: int, on_episode=None, prompt: str = DEFAULT_PROMPT,
             rules: str = "project") -> list: ...


def make_decoder(model_dir: str, *, backend: str = "hf", batch_size: int = 32, max_new_tokens: int = 4096,
                 dtype: str = "float32", trust_remote_code: bool = False,
                 attn_implementation: str | None = None) -> Decoder:
    """A decoder over a finetuned model directory (safetensors, tokenizer and chat format, as finetune saves)."""
    from pipeline.lm.models import attention_scale, load_chat_format, load_model, load_tokenizer

    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r} is not allowed; expected one of {', '.join(BACKENDS)}")
    if backend == "vllm" and (scale := attention_scale(model_dir)) != "constant":
        raise ValueError(f"backend='vllm' cannot decode {model_dir}: its model scales attention by {scale}, "
                         "which vLLM does not run; expected backend='hf'")
    fmt = load_chat_format(model_dir)
    tokenizer = load_tokenizer(model_dir, trust_remote_code=trust_remote_code)
    common = dict(batch_size=batch_size, max_new_tokens=max_new_tokens)
    if backend == "vllm":
        from pipeline.lm.decoding.vllm import VLLMDecoder

        return VLLMDecoder(model_dir, tokenizer, fmt, dtype=dtype, **common)
    import torch

    from pipeline.lm.decoding.hf import HFDecoder

    model = load_model(model_dir, dtype=dtype, trust_remote_code=trust_remote_code,
                       attn_implementation=attn_implementation)
    # Decode where the Trainer trained: on the GPU when there is one.
    return HFDecoder(model.to("cuda" if torch.cuda.is_available() else "cpu"), tokenizer, fmt, **common)
