"""Greedy decoding with a transformers causal LM: batched answers (optimal) and multi-turn episodes (reachable).

One KV cache (a `DynamicCache`) holds a batch of sequences of different lengths: rows are left-padded and may
have holes (the per-row padding of an appended chunk). The attention mask marks the real tokens and position
ids are counted from it, so every row computes what it would compute alone. A row leaves the batch as soon as
its turn ends, so finished sequences cost nothing. Each layer's keys and values have room to grow
(`_GrowingLayer`). The episode loop is `pipeline.lm.decoding.loop`.
"""

from __future__ import annotations

import inspect
from functools import lru_cache
from typing import Callable, Iterable, Sequence

import torch
from transformers import DynamicCache
from transformers.cache_utils import DynamicLayer

from pipeline.core.texts import DEFAULT_PROMPT
from pipeline.core.world import World
from pipeline.lm.chat import ChatFormat, TextTokenizer, encode_prompt, stop_ids
from pipeline.lm.decoding.loop import (
    Continuation, DecodedEpisode, Generation, HistorySequences, HistoryStrategy, MoveChooser, Request, StopReason,
    context_error,
    generation, play_episodes,
)


# ----------------------------------------------------------------------------------------------------
# HF: a batch of cached rows


class _GrowingLayer(DynamicLayer):
    """A `DynamicLayer` whose keys and values are the filled part of buffers with room to grow (twice what they
    hold when they are made): a step writes its token's keys and values in place, where `DynamicLayer`
    concatenates, copying the whole layer at every token. The same values, so the same attention (the same
    texts, checked on a split of the default job's test worlds); about 0.9x a split's decoding time there."""

    _buffers: tuple[torch.Tensor, torch.Tensor] | None = None

    def update(self, key_states: torch.Tensor, value_states: torch.Tensor, *args, **kwargs):
        if not self.is_initialized:
            self.lazy_initialization(key_states, value_states)
        held = self.keys.shape[-2] if self.keys.numel() else 0
        total = held + key_states.shape[-2]
        room = self._buffers
        if (room is None or held and room[0].data_ptr() != self.keys.data_ptr()  # replaced (a row select, a crop)
                or room[0].shape[0] != key_states.shape[0] or total > room[0].shape[2]):
            batch, heads, _, width = key_states.shape
            room = tuple(states.new_empty(batch, heads, 2 * total, width) for states in (key_states, value_states))
            if held:
                room[0][:, :, :held] = self.keys
                room[1][:, :, :held] = self.values
            self._buffers = room
        room[0][:, :, held:total] = key_states
        room[1][:, :, held:total] = value_states
        self.keys, self.values = room[0][:, :, :total], room[1][:, :, :total]
        return self.keys, self.values


def _growing(cache: DynamicCache) -> DynamicCache:
    """``cache`` with each of its plain dynamic layers (not sliding-window or other kinds) a `_GrowingLayer`."""
    for layer in cache.layers:
        if type(layer) is DynamicLayer:
            layer.__class__ = _GrowingLayer
    return cache


class _Rows:
    """Sequences sharing one `DynamicCache`; `mask` (batch, cache length) marks real tokens."""

    def __init__(self, cache: DynamicCache, mask: torch.Tensor, lengths: list[int]):
        self.cache, self.mask, self.lengths = _growing(cache), mask, lengths

    @classmethod
    def empty(cls, model, n: int) -> _Rows:
        mask = torch.zeros(n, 0, dtype=torch.long, device=model.device)
        return cls(DynamicCache(config=model.config), mask, [0] * n)

    def __len__(self) -> int:
        return len(self.lengths)

    def needs_compacting(self) -> bool:
        """Whether holes made the cache much wider than its longest row (`merge` would shrink it)."""
        slack = self.mask.shape[1] - max(self.lengths)
        return slack > max(32, self.mask.shape[1] // 8)

    def extend(self, model, chunks: Sequence[Sequence[int]], pad_id: int) -> torch.Tensor:
        """Feed one chunk per row (left-padded to a block); returns each row's next-token logits."""
        width = max(len(chunk) for chunk in chunks)
        ids = torch.full((len(chunks), width), pad_id, dtype=torch.long)
        chunk_mask = torch.zeros(len(chunks), width, dtype=torch.long)
        for row, chunk in enumerate(chunks):
            if chunk:
                ids[row, width - len(chunk):] = torch.tensor(chunk)
                chunk_mask[row, width - len(chunk):] = 1
        ids, chunk_mask = ids.to(self.mask.device), chunk_mask.to(self.mask.device)
        positions = torch.tensor(self.lengths, device=self.mask.device)[:, None] + (chunk_mask.cumsum(1) - 1).clamp(min=0)
        self.mask = torch.cat([self.mask, chunk_mask], dim=1)
        self.lengths = [n + len(chunk) for n, chunk in zip(self.lengths, chunks)]
        out = model(input_ids=ids, attention_mask=self.mask, position_ids=positions,
                    **cache_kwarg(model, self.cache), use_cache=True, logits_to_keep=1)
        return out.logits[:, -1]

    def step(self, model, tokens: Sequence[int]) -> torch.Tensor:
        """Feed one token per row; returns the next-token logits."""
        device = self.mask.device
        ids = torch.tensor(tokens, device=device)[:, None]
        positions = torch.tensor(self.lengths, device=device)[:, None]
        self.mask = torch.cat([self.mask, torch.ones_like(ids)], dim=1)
        self.lengths = [n + 1 for n in self.lengths]
        out = model(input_ids=ids, attention_mask=self.mask, position_ids=positions,
                    **cache_kwarg(model, self.cache), use_cache=True, logits_to_keep=1)
        return out.logits[:, -1]

    def select(self, rows: Sequence[int], config) -> _Rows:
        """A copy holding only `rows`, without the columns that are padding in all of them."""
        index = torch.tensor(rows, device=self.mask.device)
        mask = self.mask[index]
        real = mask.any(0).nonzero()
        start = int(real[0]) if len(real) else mask.shape[1]
        layers = [(layer.keys[index][:, :, start:], layer.values[index][:, :, start:]) for layer in self.cache.layers]
        return _Rows(DynamicCache(layers, config=config), mask[:, start:], [self.lengths[r] for r in rows])

    @staticmethod
    def merge(parts: Sequence[_Rows], config) -> _Rows:
        """All rows of `parts` in one batch, compacted: each row's real tokens right-aligned, no holes."""
        lengths = [n for part in parts for n in part.lengths]
        width = max(lengths)
        device = parts[0].mask.device
        moves = []  # per part: (source rows, source columns, destination rows, destination columns)
        base = 0
        for part in parts:
            src_rows, src_cols = part.mask.nonzero(as_tuple=True)
            rank = part.mask.cumsum(1)[src_rows, src_cols] - 1
            counts = part.mask.sum(1)
            moves.append((src_rows, src_cols, src_rows + base, width - counts[src_rows] + rank))
            base += len(part)
        layers = []
        for depth, reference in enumerate(parts[0].cache.layers):
            kv = []
            for which in ("keys", "values"):
                ref = getattr(reference, which)
                merged = ref.new_zeros(len(lengths), ref.shape[1], width, ref.shape[3])
                for part, (src_rows, src_cols, dst_rows, dst_cols) in zip(parts, moves):
                    merged[dst_rows, :, dst_cols] = getattr(part.cache.layers[depth], which)[src_rows, :, src_cols]
                kv.append(merged)
            layers.append(tuple(kv))
        mask = (torch.arange(width, device=device)[None, :]
                >= width - torch.tensor(lengths, device=device)[:, None]).long()
        return _Rows(DynamicCache(layers, config=config), mask, lengths)


def cache_kwarg(model, cache) -> dict:
    """The cache as the model's forward names it: ``cache`` in current transformers 5 releases (which warn
    that ``past_key_values`` goes in 5.40), ``past_key_values`` in earlier ones."""
    return {_cache_name(type(model)): cache}


@lru_cache(maxsize=None)
def _cache_name(model_class: type) -> str:
    parameters = inspect.signature(model_class.forward).parameters
    for name in ("cache", "past_key_values"):
        if name in parameters:
            return name
    # A wrapper that passes **kwargs on: the name transformers' own models take.
    from transformers import LlamaForCausalLM

    return "cache" if "cache" in inspect.signature(LlamaForCausalLM.forward).parameters else "past_key_values"


class HFDecoder:
    """Greedy decoding with a transformers causal LM (full-attention layers), batched with a KV cache.

    `max_new_tokens` caps an optimal-setting answer and a first reachable answer; `max_followup_tokens`
    caps the later (bare move) answers. `max_length` (default: the model's `max_position_embeddings`)
    bounds prompt plus generated tokens; an item that does not fit gets an error, never an exception.
    """

    def __init__(
        self,
        model,
        tokenizer: TextTokenizer,
        fmt: ChatFormat,
        *,
        batch_size: int = 16,
        max_new_tokens: int = 4096,
        max_followup_tokens: int = 64,
        max_length: int | None = None,
    ):
        if batch_size < 1 or max_new_tokens < 1 or max_followup_tokens < 1:
            raise ValueError("batch_size, max_new_tokens and max_followup_tokens must be at least 1")
        layer_types = getattr(model.config.get_text_config(decoder=True), "layer_types", None) or []
        if any(kind != "full_attention" for kind in layer_types):
            raise ValueError("HFDecoder supports full-attention models only (its cache rows are compacted by hand)")
        self.model = model.eval()
        self.tokenizer, self.fmt = tokenizer, fmt
        self.batch_size, self.max_new_tokens, self.max_followup_tokens = batch_size, max_new_tokens, max_followup_tokens
        self.max_length = max_length or model.config.max_position_embeddings
        self.stop_ids = stop_ids(tokenizer, fmt)
        if not self.stop_ids:
            raise ValueError("the chat format has an empty turn_end: decoding could never stop")
        pad = getattr(tokenizer, "pad_token_id", None)
        self.pad_id = pad if pad is not None else 0

    # -- optimal setting ------------------------------------------------------------------------------

    def generate(self, prompts: Sequence[Sequence[dict]], max_new_tokens: int | None = None) -> list[Generation]:
        """Greedy answers to conversations (each ending with a human turn), in input order.

        Prompts are sorted by length into batches; a sequence leaves its batch when its turn ends.
        """
        cap = max_new_tokens or self.max_new_tokens
        encoded = [encode_prompt(self.tokenizer, self.fmt, turns) for turns in prompts]
        results: list[Generation | None] = [None] * len(encoded)
        fitting = []
        for i, ids in enumerate(encoded):
            if len(ids) >= self.max_length:
                results[i] = Generation("", 0, False, "error", context_error(len(ids), self.max_length))
            else:
                fitting.append(i)
        fitting.sort(key=lambda i: len(encoded[i]))
        with torch.inference_mode():
            for start in range(0, len(fitting), self.batch_size):
                batch = fitting[start:start + self.batch_size]
                outs = self._continue_batch([encoded[i] for i in batch], [cap] * len(batch))
                for i, out in zip(batch, outs):
                    results[i] = generation(self.tokenizer, out)
        return results

    # -- reachable setting ----------------------------------------------------------------------------

    def play(
        self,
        worlds: Sequence[World],
        *,
        max_moves: int = 200,
        on_episode: Callable[[DecodedEpisode], None] | None = None,
        strategy: HistoryStrategy = "cached",
        choose_move: MoveChooser | None = None,
        prompt: str = DEFAULT_PROMPT,
        rules: str = "project",
    ) -> list[DecodedEpisode]:
        """Play every world's episode, `batch_size` at a time, each keeping its KV cache across turns.

        `strategy` "reencode" (batched, history re-encoded every turn) and "generate" (one `model.generate`
        per episode turn) are the baselines the benchmark compares against; `choose_move` replaces the
        answer parser (benchmarks use it to force multi-turn episodes out of an untrained model).
        """
        if strategy == "cached":
            backend = _CachedSequences(self)
        else:
            continue_prompts = self._continue_batch if strategy == "reencode" else self._continue_one_by_one
            backend = HistorySequences(continue_prompts, self.stop_ids, self.max_length)
        with torch.inference_mode():
            return play_episodes(
                backend, self.tokenizer, self.fmt, worlds,
                batch_size=1 if strategy == "generate" else self.batch_size,
                max_moves=max_moves, max_new_tokens=self.max_new_tokens,
                max_followup_tokens=self.max_followup_tokens, on_episode=on_episode, choose_move=choose_move,
                prompt=prompt, rules=rules,
            )

    # -- the engine -----------------------------------------------------------------------------------

    def _continue_batch(self, prompts: list[list[int]], caps: list[int]) -> list[Continuation]:
        """Whole prompts (each shorter than max_length) continued as one batch, no cache kept."""
        rows, logits = self._prefill(None, prompts)
        return self._decode(rows, logits, caps, keep=False)[0]

    def _continue_one_by_one(self, prompts: list[list[int]], caps: list[int]) -> list[Continuation]:
        """Baseline: one `model.generate` call per prompt (a one-token turn end)."""
        if len(self.stop_ids) != 1:
            raise ValueError("the generate baseline needs a one-token turn end")
        results = []
        for prompt, cap in zip(prompts, caps):
            ids = torch.tensor([prompt], device=self.model.device)
            room = self.max_length - len(prompt)
            out = self.model.generate(ids, attention_mask=torch.ones_like(ids), do_sample=False,
                                      max_new_tokens=min(cap, room), eos_token_id=self.stop_ids[0],
                                      pad_token_id=self.pad_id)[0, len(prompt):].tolist()
            if out[-1:] == self.stop_ids:
                results.append(Continuation(out[:-1], "turn_end", n_stop=1))
            else:
                results.append(Continuation(out, "max_new_tokens" if len(out) >= cap else "context"))
        return results

    def _prefill(self, rows: _Rows | None, chunks: Sequence[Sequence[int]]) -> tuple[_Rows, torch.Tensor]:
        """Append one chunk per row to `rows` (None: new rows); returns the rows and next-token logits."""
        rows = _Rows.empty(self.model, len(chunks)) if rows is None else rows
        return rows, rows.extend(self.model, chunks, self.pad_id)

    def _decode(
        self, rows: _Rows, logits: torch.Tensor, caps: Sequence[int], *, keep: bool
    ) -> tuple[list[Continuation], tuple[_Rows, list[int]] | None]:
        """Decode greedily from `logits` until every row stopped; a row leaves the batch when it stops.

        With `keep`, the stopped rows are merged back (compacted) and returned with their order (row
        indices of the input); each row's last generated token is then not in the cache yet, so it must
        lead the row's next chunk.
        """
        config = self.model.config
        active = list(range(len(rows)))  # active[j]: the input row of batch row j
        generated: list[list[int]] = [[] for _ in active]
        reasons: list[StopReason | None] = [None] * len(active)
        parked: list[_Rows] = []
        parked_order: list[int] = []
        n_stop = len(self.stop_ids)
        while True:
            tokens = logits.argmax(-1).tolist()
            stopped = []
            for j, (i, token) in enumerate(zip(active, tokens)):
                ids = generated[i]
                ids.append(token)
                if ids[-n_stop:] == self.stop_ids:
                    reasons[i] = "turn_end"
                elif len(ids) >= caps[i]:
                    reasons[i] = "max_new_tokens"
                elif rows.lengths[j] + 1 >= self.max_length:
                    reasons[i] = "context"
                if reasons[i] is not None:
                    stopped.append(j)
            if stopped:
                going = [j for j in range(len(active)) if reasons[active[j]] is None]
                if keep:
                    parked.append(rows.select(stopped, config) if going else rows)
                    parked_order += [active[j] for j in stopped]
                if not going:
                    break
                rows = rows.select(going, config)
                active = [active[j] for j in going]
                tokens = [tokens[j] for j in going]
            logits = rows.step(self.model, tokens)
        decoded = [
            Continuation(ids[:-n_stop], reason, n_stop=n_stop) if reason == "turn_end" else Continuation(ids, reason)
            for ids, reason in zip(generated, reasons)
        ]
        if not keep:
            return decoded, None
        # Compacting copies the whole cache: do it only when holes have made it much wider.
        whole = len(parked) == 1 and not parked[0].needs_compacting()
        return decoded, (parked[0] if whole else _Rows.merge(parked, config), parked_order)


class _CachedSequences:
    """HFDecoder's backend for episodes: one cache for all live sequences, extended turn after turn."""

    def __init__(self, decoder: HFDecoder):
        self.decoder = decoder
        self.rows: _Rows | None = None
        self.keys: list[int] = []  # the key of each cache row
        self.unfed: dict[int, list[int]] = {}  # generated ids not in the cache yet

    def release(self, keys: Iterable[int]) -> None:
        gone = set(keys)
        keep = [r for r, key in enumerate(self.keys) if key not in gone]
        if len(keep) == len(self.keys):
            return
        for key in gone:
            self.unfed.pop(key, None)
        self.rows = self.rows.select(keep, self.decoder.model.config) if keep else None
        self.keys = [self.keys[r] for r in keep]

    def continue_sequences(self, requests: dict[int, Request]) -> dict[int, Continuation]:
        dec = self.decoder
        missing = set(self.keys) - set(requests)
        if missing:
            raise ValueError(f"every live sequence must be continued; no request for {sorted(missing)}")
        chunks = {key: self.unfed.pop(key, []) + list(req.ids) for key, req in requests.items()}
        lengths = dict(zip(self.keys, self.rows.lengths)) if self.rows is not None else {}
        results: dict[int, Continuation] = {}
        for key, chunk in chunks.items():
            total = lengths.get(key, 0) + len(chunk)
            if total >= dec.max_length:
                results[key] = Continuation([], "error", context_error(total, dec.max_length))
        self.release(results)
        old = list(self.keys)
        new = [key for key in requests if key not in results and key not in lengths]
        if not old and not new:
            return results
        # Old rows extend their cache with a short followup, new rows are prefilled on their own (so old
        # rows never pad up to a whole prompt); then one batch decodes them all.
        parts, logits = [], []
        for keys, rows in ((old, self.rows), (new, None)):
            if keys:
                rows, part_logits = dec._prefill(rows, [chunks[k] for k in keys])
                parts.append(rows)
                logits.append(part_logits)
        rows = parts[0] if len(parts) == 1 else _Rows.merge(parts, dec.model.config)
        keys = old + new
        decoded, (self.rows, order) = dec._decode(rows, torch.cat(logits), [requests[k].max_new_tokens for k in keys],
                                                  keep=True)
        self.keys = [keys[i] for i in order]
        for key, out in zip(keys, decoded):
            # The last generated token is not in the cache yet; it leads the next chunk.
            self.unfed[key] = dec.stop_ids[-1:] if out.stop_reason == "turn_end" else out.ids[-1:]
            results[key] = out
        return results
