"""The last decoder layer computed only where the loss reads it (`TrainSettings.labelled_last_layer`).

A causal LM's loss reads the last layer's output at the positions whose next token is labelled: on the CPU
default, every position from the answer's first token on, and about a third of a conversation's tokens (the
prompt) come before it. Every earlier layer feeds the later positions through attention's keys and values, so it
runs everywhere; the last one needs its keys and values everywhere, but its queries, attention output, MLP and
norms only from the first position any row of the batch trains on (`start_of_labels`). The same loss and
gradients in exact arithmetic, rounded otherwise: on an AVX2-only CPU (fp32) 0.92x to 0.96x a batch part's
forward and backward on one thread, 0.94x the default's training step (README, Speed).

For transformers' Llama with eager attention (`trims`): `hidden_from` runs the model's own modules, every layer
through `layer_rows` (the last from the start, the others from 0), compiled the way the blocks are
(`pipeline.lm.training.compile.compiled_blocks`): one graph for all of them, as the layer's own was. Its inputs
are copies cut outside the graph: a start traced inside it was specialized at the first layer's 0, and the last
layer compiled apart, about 30 s more compiling beside the data-build on that CPU (docs/speed.md).
"""

from __future__ import annotations

import torch
from transformers.masking_utils import create_causal_mask
from transformers.models.llama.modeling_llama import eager_attention_forward, rotate_half

# Base models whose forward `hidden_from` reproduces (embedding, rotary positions, the decoder layers, final norm).
TRIMMED_MODELS = ("LlamaModel",)


def trims(base: torch.nn.Module) -> bool:
    """Whether `hidden_from` computes ``base``'s forward: a Llama base model with eager attention (whose causal mask
    is a tensor that rows of queries can be cut from) and its layers a plain ModuleList (not compiled stacked,
    which runs them as one call)."""
    return (type(base).__name__ in TRIMMED_MODELS and base.config._attn_implementation == "eager"
            and type(base.layers) is torch.nn.ModuleList)


def not_cut(base: torch.nn.Module, stacked: bool) -> str | None:
    """Why a training of ``base`` (its layers compiled ``stacked`` or not) keeps its whole last layer, or None."""
    if stacked or not trims(base):
        return (f"{type(base).__name__} with {base.config._attn_implementation} attention"
                f"{', compiled stacked,' if stacked else ''} is not a model whose last layer is cut "
                f"({', '.join(TRIMMED_MODELS)} with eager attention, not compiled stacked)")
    return None


def start_of_labels(keep: torch.Tensor) -> int:
    """The first position whose next token some row trains on (``keep``: rows x positions, True where the next
    token is labelled); 0 where none is."""
    columns = keep.any(dim=0)
    return int(columns.to(torch.int8).argmax()) if keep.numel() else 0


def hidden_from(base: torch.nn.Module, inputs: dict[str, torch.Tensor], start: int) -> torch.Tensor:
    """``base(**inputs).last_hidden_state[:, start:]`` (``inputs``: ``input_ids`` and optional ``attention_mask``
    and ``position_ids``), the last layer computed from position ``start`` on alone (`layer_rows`)."""
    embeds = base.embed_tokens(inputs["input_ids"])
    position_ids = inputs.get("position_ids")
    if position_ids is None:
        position_ids = torch.arange(embeds.shape[1], device=embeds.device).unsqueeze(0)
    mask = create_causal_mask(config=base.config, inputs_embeds=embeds, attention_mask=inputs.get("attention_mask"),
                              cache=None, position_ids=position_ids)
    rotary = base.rotary_emb(embeds, position_ids=position_ids)
    layers = base.layers[:base.config.num_hidden_layers]
    compile_region = getattr(base.layers, "compile_region", None)
    run = compile_region(layer_rows) if compile_region is not None else layer_rows
    cos, sin = rotary
    # Each input a tensor of its own, contiguous, for every layer alike: one compiled graph serves them all (a start
    # traced at 0, or a view of another input, would be compiled apart). The rotary and mask rows are cut once.
    rows_from = {at: ((_copy(cos[:, at:]), _copy(sin[:, at:])), _copy(mask[:, :, at:])) for at in {0, start}}
    hidden = embeds
    for i, layer in enumerate(layers):
        at = start if i == len(layers) - 1 else 0
        hidden = run(layer, hidden, _copy(hidden[:, at:]), rotary, *rows_from[at])
    return base.norm(hidden)


def _copy(tensor: torch.Tensor) -> torch.Tensor:
    return tensor.clone(memory_format=torch.contiguous_format)


def layer_rows(layer: torch.nn.Module, hidden: torch.Tensor, rows: torch.Tensor,
               rotary: tuple[torch.Tensor, torch.Tensor], rotary_rows: tuple[torch.Tensor, torch.Tensor],
               mask_rows: torch.Tensor) -> torch.Tensor:
    """A Llama decoder layer's output at the last positions, ``rows`` (its input there), given its input at every
    position, ``hidden``: its keys and values from all of them, its queries and everything after attention at
    ``rows`` alone (transformers' LlamaDecoderLayer and eager attention, the queries cut). ``rotary_rows`` and
    ``mask_rows``: the rotary embedding's and the causal mask's rows at those positions."""
    attention = layer.self_attn

    def heads(states: torch.Tensor) -> torch.Tensor:
        return states.view(*states.shape[:2], -1, attention.head_dim).transpose(1, 2)

    def rotated(states: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
        return states * cos.unsqueeze(1) + rotate_half(states) * sin.unsqueeze(1)

    normed = layer.input_layernorm(hidden)
    query = rotated(heads(attention.q_proj(layer.input_layernorm(rows))), *rotary_rows)
    key = rotated(heads(attention.k_proj(normed)), *rotary)
    out, _ = eager_attention_forward(attention, query, key, heads(attention.v_proj(normed)), mask_rows,
                                     scaling=attention.scaling,
                                     dropout=attention.attention_dropout if attention.training else 0.0)
    hidden = rows + attention.o_proj(out.reshape(*rows.shape[:2], -1))
    return hidden + layer.mlp(layer.post_attention_layernorm(hidden))
