"""eval: prompt a model with each test world, score what it does, and keep one record per episode.

Records are appended to a partial file as episodes finish, so an interrupted eval resumes from its
completed episodes; the finished eval orders them by world index. Metrics are computed from the records
alone (the report recomputes its splits from the same records).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Protocol, Sequence

from tqdm import tqdm

from pipeline.core.environment import Outcome
from pipeline.core.map_errors import first_wrong_line
from pipeline.core.scoring import score_optimal
from pipeline.core.texts import prompt_turns
from pipeline.core.world import World

_STAT_FIELDS = ("size_x", "size_y", "optimal_length", "dead_ends", "up_right_only", "interpolated")


class Decoder(Protocol):
    """What eval needs of a decoding backend (pipeline.lm.decoding.hf.HFDecoder, pipeline.lm.decoding.vllm.VLLMDecoder)."""

    def answer(self, prompts: list[list[dict]]) -> list: ...

    def play(self, worlds: list[World], *, max_steps: int, on_episode=None, prompt: str = "paper") -> list: ...


def make_decoder(cfg, model_dir: str) -> Decoder:
    """The configured decoding backend over a finetuned model directory (safetensors, tokenizer, chat format)."""
    from pipeline.lm.models import load_chat_format, load_model, load_tokenizer

    fmt = load_chat_format(model_dir)
    tokenizer = load_tokenizer(model_dir, trust_remote_code=cfg.model.trust_remote_code)
    common = dict(batch_size=cfg.eval.batch_size, max_new_tokens=cfg.eval.max_new_tokens)
    if cfg.eval.backend.value == "vllm":
        from pipeline.lm.decoding.vllm import VLLMDecoder

        return VLLMDecoder(model_dir, tokenizer, fmt, dtype=cfg.model.dtype, **common)
    import torch

    from pipeline.lm.decoding.hf import HFDecoder

    model = load_model(model_dir, dtype=cfg.model.dtype, trust_remote_code=cfg.model.trust_remote_code,
                       attn_implementation=cfg.model.attn_implementation)
    # Decode where the Trainer trained: on the GPU when there is one.
    return HFDecoder(model.to("cuda" if torch.cuda.is_available() else "cpu"), tokenizer, fmt, **common)


def _base_record(index: int, stats: dict) -> dict:
    return {"world_index": index, **{key: stats[key] for key in _STAT_FIELDS}}


def optimal_record(index: int, world: World, stats: dict, text: str, error: str | None, direction: str, variant: str) -> dict:
    """Score one single-turn answer (SPEC 4, graded)."""
    record = _base_record(index, stats)
    if error is not None:
        return {**record, "success": False, "outcome": "error", "n_moves": 0, "moves": [], "parsed": False,
                "valid": False, "reaches_goal": False, "map_exact": None, "map_first_error": None,
                "first_wrong_line": None, "answers": [text], "error": error}
    score = score_optimal(world, text, direction, variant)
    wrong = first_wrong_line(world, direction, variant, text)
    moves = list(score.moves)
    return {
        **record,
        "success": bool(score.optimal),
        "outcome": "success" if score.optimal else "fail",
        "n_moves": len(moves),
        "moves": moves,
        "parsed": score.parsed,
        "valid": score.valid,
        "reaches_goal": score.reaches_goal,
        "map_exact": score.map_exact,
        "map_first_error": score.map_first_error,
        "first_wrong_line": wrong.to_dict() if wrong is not None else None,
        "answers": [text],
        "error": None,
    }


def reachable_record(index: int, stats: dict, outcome: str | None, moves: Sequence[str], error: str | None,
                     answers: Sequence[str] = ()) -> dict:
    """Record one multi-turn episode (SPEC 4 outcomes) with the model's answer of every turn."""
    return {
        **_base_record(index, stats),
        "success": outcome == Outcome.SUCCESS.value and error is None,
        "outcome": "error" if error is not None else outcome,
        "n_moves": len(moves),
        "moves": list(moves),
        "parsed": None, "valid": None, "reaches_goal": None, "map_exact": None, "map_first_error": None,
        "first_wrong_line": None, "answers": list(answers),
        "error": error,
    }


class PartialRecords:
    """An append-only JSONL of finished episodes; survives a killed process (a torn last line is dropped)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.records: dict[int, dict] = {}
        torn = False
        if self.path.exists():
            text = self.path.read_text(errors="replace")
            torn = bool(text) and not text.endswith("\n")
            for line in text.splitlines():
                try:
                    record = json.loads(line)
                    self.records[int(record["world_index"])] = record
                except (json.JSONDecodeError, KeyError, TypeError, ValueError):
                    torn = True
        if torn:  # rewrite without the torn line, so the next append does not glue onto it
            self.path.write_text("".join(json.dumps(self.records[i]) + "\n" for i in sorted(self.records)))
        self._handle = open(self.path, "a")

    def add(self, record: dict) -> None:
        self.records[record["world_index"]] = record
        self._handle.write(json.dumps(record) + "\n")
        self._handle.flush()

    def close(self) -> None:
        self._handle.close()

    def ordered(self) -> list[dict]:
        return [self.records[i] for i in sorted(self.records)]


def evaluate(
    decoder: Decoder,
    worlds: list[World],
    stats: list[dict],
    *,
    mode: str,
    direction: str,
    variant: str,
    max_steps: int,
    partial_path: str | Path,
    chunk_size: int = 64,
    prompt: str = "paper",
) -> list[dict]:
    """Run every world not yet in ``partial_path`` and return all records in world order.

    Chunks are fixed blocks of world indices, so a resumed eval batches the worlds it still has to do
    exactly as an uninterrupted one would (optimal-setting records are written a whole chunk at a time,
    so its finished chunks are skipped whole and the rest decode in the very same batches).
    """
    partial = PartialRecords(partial_path)
    done = sum(1 for i in range(len(worlds)) if i in partial.records)
    progress = tqdm(total=len(worlds), initial=done, desc=f"eval {mode}", unit="world")
    try:
        for start in range(0, len(worlds), chunk_size):
            chunk = [i for i in range(start, min(start + chunk_size, len(worlds))) if i not in partial.records]
            if not chunk:
                continue
            if mode == "optimal":
                generations = decoder.answer([prompt_turns(worlds[i], prompt) for i in chunk])
                for i, generation in zip(chunk, generations):
                    partial.add(optimal_record(i, worlds[i], stats[i], generation.text, generation.error, direction, variant))
                    progress.update()
            else:
                def finished(episode, chunk=chunk) -> None:
                    i = chunk[episode.world_index]
                    outcome = episode.outcome.value if episode.outcome is not None else None
                    partial.add(reachable_record(i, stats[i], outcome, episode.moves, episode.error, episode.answers))
                    progress.update()

                decoder.play([worlds[i] for i in chunk], max_steps=max_steps, on_episode=finished, prompt=prompt)
    finally:
        progress.close()
        partial.close()
    return partial.ordered()


def _rate(records: Iterable[dict], predicate) -> float | None:
    records = list(records)
    return sum(1 for r in records if predicate(r)) / len(records) if records else None


def metrics(records: list[dict]) -> dict[str, float]:
    """The eval run's metrics (names in tracking.EVAL_METRICS); rates over empty subsets are left out."""
    interp = [r for r in records if r["interpolated"]]
    extrap = [r for r in records if not r["interpolated"]]
    values = {
        "n_episodes": float(len(records)),
        "success_rate": _rate(records, lambda r: r["success"]),
        "success_rate_interp": _rate(interp, lambda r: r["success"]),
        "success_rate_extrap": _rate(extrap, lambda r: r["success"]),
        "rate_error": _rate(records, lambda r: r["outcome"] == "error"),
    }
    for outcome in (Outcome.DEADEND, Outcome.MAX_STEP, Outcome.INVALID):
        values[f"rate_{outcome.value}"] = _rate(records, lambda r, o=outcome.value: r["outcome"] == o)
    for field in ("parsed", "valid", "reaches_goal", "map_exact"):
        graded = [r for r in records if r[field] is not None]
        if graded:
            values[f"rate_{field}"] = _rate(graded, lambda r, f=field: bool(r[f]))
    return {key: value for key, value in values.items() if value is not None}
