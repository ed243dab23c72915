"""data-build: the world splits and their conversations, written as files (the step logs them to MLflow).

The splits depend only on the data config, so every variant is trained and tested on the same worlds;
the texts depend on (direction, variant, mode) as well. Files are written in a fixed order with fixed
formatting, so the same config gives byte-identical files (their SHA-256 is logged).
"""

from __future__ import annotations

import hashlib
import json
import statistics
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Iterable, Sequence

from tqdm import tqdm

from pipeline.core.generation import GeneratorConfig, generate_worlds, world_stats
from pipeline.lm.tokenizer import count_pieces
from pipeline.core.world import World, load_worlds, save_worlds
from pipeline.core.texts import conversation

TRAIN_WORLDS, TEST_WORLDS = "worlds/train.jsonl", "worlds/test.jsonl"
TRAIN_CONVERSATIONS, TEST_CONVERSATIONS = "conversations/train.jsonl", "conversations/test.jsonl"
TEST_STATS = "stats/test_worlds.jsonl"
SUMMARY = "stats/summary.json"


@dataclass(frozen=True)
class TextSpec:
    """What decides the texts of a dataset besides its worlds. ``direction`` is None where it has no effect."""

    direction: str | None
    variant: str
    mode: str
    seed: int = 0
    prompt: str = "paper"   # texts.PROMPTS: the paper's three prompt turns, or the task turn alone

    @classmethod
    def of(cls, direction: str, variant: str, mode: str, seed: int = 0, prompt: str = "paper") -> "TextSpec":
        # NONE and DFS texts do not depend on the direction: both directions share one dataset (and model).
        return cls(None if variant in ("none", "dfs") else direction, variant, mode, seed, prompt)


def generator_config(size_x: Sequence[int], size_y: Sequence[int], frame: int, p_pit: Sequence[float]) -> GeneratorConfig:
    return GeneratorConfig(size_x=tuple(size_x), size_y=tuple(size_y), frame=frame, p_pit=tuple(p_pit))


def build_splits(data) -> tuple[list[World], list[World]]:
    """(train, test) worlds for a data config: test generated (or the given file), train disjoint from it."""
    if data.test_file:
        source = Path(data.test_file).expanduser()
        if not source.is_file():
            raise FileNotFoundError(f"data.test_file={data.test_file!r}: no such file; expected a JSONL of worlds "
                                    f"in the paper's schema (one {{\"question\": {{...}}}} per line)")
        test = load_worlds(source)
        if not test:
            raise ValueError(f"data.test_file={data.test_file!r} holds no worlds; expected at least data.n_test="
                             f"{data.n_test}")
        if len(test) < data.n_test:
            raise ValueError(
                f"data.n_test={data.n_test} but {data.test_file} holds only {len(test)} worlds; "
                f"allowed: 1..{len(test)}"
            )
        test = test[: data.n_test]
    else:
        test_cfg = generator_config(data.test_size_x, data.test_size_y, data.frame, data.p_pit)
        test = generate_worlds(data.n_test, data.seed, test_cfg, split="test", workers=data.workers)
    train_cfg = generator_config(data.train_size_x, data.train_size_y, data.frame, data.p_pit)
    exclude = frozenset(world.key() for world in test)
    train = generate_worlds(data.n_train, data.seed, train_cfg, split="train", exclude=exclude, workers=data.workers)
    return train, test


def _write_jsonl(path: Path, rows: Iterable[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        for row in rows:
            handle.write(json.dumps(row, separators=(", ", ": ")) + "\n")


def _conversations(worlds: list[World], spec: TextSpec, desc: str) -> Iterable[dict]:
    direction = spec.direction or "fwd"
    for index, world in enumerate(tqdm(worlds, desc=desc, unit="world", leave=False)):
        # Each world's DFS walk gets its own seed, so the walks do not depend on the split's order.
        turns = conversation(world, direction, spec.variant, spec.mode, seed=spec.seed * 1_000_003 + index,
                             prompt=spec.prompt)
        yield {"id": index, "conversations": turns}


def _summary(values: list[int]) -> dict:
    return {"mean": statistics.fmean(values), "max": max(values), "min": min(values)} if values else {}


def write_dataset(out_dir: str | Path, train: list[World], test: list[World], spec: TextSpec, train_max: tuple[int, int]) -> dict:
    """Write worlds, conversations and stats under ``out_dir``; return the summary (also written)."""
    out = Path(out_dir)
    (out / "worlds").mkdir(parents=True, exist_ok=True)
    save_worlds(out / TRAIN_WORLDS, train)
    save_worlds(out / TEST_WORLDS, test)
    token_lengths: list[int] = []

    def measured(rows: Iterable[dict]) -> Iterable[dict]:
        for row in rows:
            token_lengths.append(sum(count_pieces(turn["value"]) + 2 for turn in row["conversations"]))
            yield row

    _write_jsonl(out / TRAIN_CONVERSATIONS, measured(_conversations(train, spec, "train texts")))
    train_tokens = list(token_lengths)
    # Test conversations are the golden references (the model is prompted with their turns before the first answer).
    _write_jsonl(out / TEST_CONVERSATIONS, _conversations(test, spec, "test texts"))
    test_stats = [asdict(world_stats(world, train_max)) for world in test]
    _write_jsonl(out / TEST_STATS, test_stats)
    summary = {
        "text_spec": asdict(spec),
        "n_train": len(train),
        "n_test": len(test),
        "train_tokens": _summary(train_tokens),
        "train_path_length": _summary([len(w.optimal_moves()) for w in train]),
        "test_path_length": _summary([s["optimal_length"] for s in test_stats]),
        "test_up_right_only": sum(s["up_right_only"] for s in test_stats) / max(len(test_stats), 1),
        "test_interpolated": sum(s["interpolated"] for s in test_stats) / max(len(test_stats), 1),
        "sha256": dataset_sha256(out),
    }
    (out / SUMMARY).write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    return summary


def dataset_sha256(out_dir: str | Path) -> str:
    """One hash over the dataset's data files (not the summary), in a fixed order."""
    digest = hashlib.sha256()
    for name in (TRAIN_WORLDS, TEST_WORLDS, TRAIN_CONVERSATIONS, TEST_CONVERSATIONS, TEST_STATS):
        digest.update(name.encode())
        digest.update((Path(out_dir) / name).read_bytes())
    return digest.hexdigest()


def read_conversations(path: str | Path) -> list[list[dict]]:
    """Conversations from JSONL, in order: each line a list of turns or an object with a ``conversations`` list."""
    conversations = []
    with open(path) as lines:
        for number, line in enumerate(lines, 1):
            if not line.strip():
                continue
            record = json.loads(line)
            turns = record["conversations"] if isinstance(record, dict) else record
            if not isinstance(turns, list):
                raise ValueError(f"{path}:{number}: expected a list of turns or {{'conversations': [...]}}")
            conversations.append(turns)
    return conversations
