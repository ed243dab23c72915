"""data-build: the world splits and their conversations, written as files (the step logs them to MLflow).

The splits depend only on the data config, so every variant is trained and tested on the same worlds;
the texts depend on (direction, variant, mode) as well. Files are written in a fixed order with fixed
formatting, so the same config gives byte-identical files (their SHA-256 is logged).
"""

from __future__ import annotations

import hashlib
import json
import statistics
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Iterable, Optional

import mlflow
from tqdm import tqdm

from pipeline.core.bulk import bulk_building
from pipeline.core.generators import GeneratorConfig, check_deep, check_ranges, generate_worlds, world_stats
from pipeline.core.texts import DEFAULT_PROMPT, conversation, edge_label_spans, listed_obstacles
from pipeline.core.variants import BY_NAME, text_direction
from pipeline.core.world import World, load_worlds, save_worlds
from pipeline.lm.chat import UNTRAINED
from pipeline.lm.tokenizer import piece_census, piece_set
from pipeline.workflow.paper_data import PAPER_WORD, ResolvedFile, file_sha256, resolve
from pipeline.workflow.steps import StepRun
from pipeline.workflow.tracking import log_dataset, log_settings
from pipeline.core.checks import require

TRAIN_WORLDS, TEST_WORLDS = "worlds/train.jsonl", "worlds/test.jsonl"
TRAIN_CONVERSATIONS, TEST_CONVERSATIONS = "conversations/train.jsonl", "conversations/test.jsonl"
TEST_STATS = "stats/test_worlds.jsonl"
SUMMARY = "stats/summary.json"


@dataclass
class DataSettings:
    """The worlds of a job: the train and test splits' sizes, obstacles and counts (the paper's sampling
    by default). ``frame`` bounds every coordinate; ``test_file`` takes the test split from a file of worlds
    in the paper's schema instead of generating it. The defaults are the base of the ``conf/data`` presets.

    What the generator takes defaults to `GeneratorConfig`'s defaults (the test sizes are the data's own) and is
    checked as `GeneratorConfig` checks it (`check_ranges`), both splits at once."""

    train_size_x: list[int] = field(default_factory=lambda: list(GeneratorConfig.size_x))
    train_size_y: list[int] = field(default_factory=lambda: list(GeneratorConfig.size_y))
    # The paper's test worlds: sides up to twice the train sides'.
    test_size_x: list[int] = field(default_factory=lambda: [2, 20])
    test_size_y: list[int] = field(default_factory=lambda: [2, 20])
    frame: int = GeneratorConfig.frame
    p_pit: list[float] = field(default_factory=lambda: list(GeneratorConfig.p_pit))
    n_train: int = 50_000
    n_test: int = 3_000
    # The test split from a file of worlds in the paper's schema instead of generated ones: a path, or "paper"
    # for the paper's released 3,000 test worlds (fetched once, checksummed; pipeline.workflow.paper_data).
    test_file: Optional[str] = None
    # The train split from a file likewise: a path, or "paper" for the paper's released 50,000 train worlds
    # (an exact reproduction; the first n_train are used, none excluded).
    train_file: Optional[str] = None
    seed: int = 0
    workers: int = 2
    generator: str = GeneratorConfig.generator   # pipeline.core.generators: "project" or "paper"
    # Not in the paper: the fraction of train worlds drawn deep (`GeneratorConfig.deep`: start and goal at the
    # ends of the free tree's longest path, so the same sides hold longer paths); validation and test stay
    # the paper's (corner to corner).
    train_deep: float = field(default=0.0, metadata={"hash_if_set": True})
    # Not in the paper: each train prompt's pit and wall lists also hold up to this many cells of the frame
    # outside the grid (`texts.listed_obstacles`), so the lists are as long as a larger world's; the worlds,
    # answers, validation and test texts are unchanged.
    train_distractors: int = field(default=0, metadata={"hash_if_set": True})
    # Not in the paper: the labels of neighbours just outside a train grid as long as the largest train grid on
    # that axis are no loss targets (`texts.edge_label_spans`: the train worlds cannot tell "beyond the bound"
    # from "too far from the corner" there); the texts themselves are unchanged.
    mask_edge_labels: bool = field(default=False, metadata={"hash_if_set": True})

    def __post_init__(self) -> None:
        # As lists, so a message writes a range the same way whether it came as a list, a tuple or from the config.
        sizes = ("train_size_x", "train_size_y", "test_size_x", "test_size_y")
        check_ranges(self.generator, self.frame, list(self.p_pit), {name: list(getattr(self, name)) for name in sizes})
        check_deep(self.generator, self.train_deep, "train_deep")
        for name in ("n_train", "n_test", "workers"):
            require(getattr(self, name) >= 1, name, getattr(self, name), "at least 1")
        require(isinstance(self.train_distractors, int) and self.train_distractors >= 0, "train_distractors",
                self.train_distractors, "an integer >= 0 (0: the world's own lists)")

    @property
    def train_max(self) -> tuple[int, int]:
        """The largest train world sides (X, Y): test worlds within both are interpolated."""
        return max(self.train_size_x), max(self.train_size_y)

    def generator_config(self, split: str) -> GeneratorConfig:
        """The generator settings of the ``train`` or ``test`` split."""
        size_x, size_y = (self.train_size_x, self.train_size_y) if split == "train" else (self.test_size_x, self.test_size_y)
        return GeneratorConfig(size_x=tuple(size_x), size_y=tuple(size_y), frame=self.frame,
                               p_pit=tuple(self.p_pit), generator=self.generator,
                               deep=self.train_deep if split == "train" else 0.0)


@dataclass(frozen=True)
class TextSettings:
    """What decides the texts of a dataset besides its worlds. ``direction`` is None where it has no effect."""

    direction: str | None
    variant: str
    mode: str
    seed: int = 0
    prompt: str = DEFAULT_PROMPT   # texts.PROMPTS: the paper's three prompt turns, or the task turn alone
    # texts.STEP_HEADERS: `Step k:` (the paper's) or `Step:`; in the data-build hash only when set.
    step_headers: str = field(default="numbered", metadata={"hash_if_set": True})
    # How the word-level tokenizer cuts numbers (ModelSettings.numbers): not the texts, but the pieces the
    # summary counts (tokens, untrained words); in the data-build hash only when set.
    numbers: str = field(default="whole", metadata={"hash_if_set": True})
    # texts.PLAN_FORMS: the paper's Plan of moves, or anchored (each move after the cell it leaves); in the
    # data-build hash only when set.
    plan_form: str = field(default="moves", metadata={"hash_if_set": True})
    # Where the word-level tokenizer puts a newline (ModelSettings.newlines): as `numbers`, the pieces the summary
    # counts; in the data-build hash only when set.
    newlines: str = field(default="own", metadata={"hash_if_set": True})
    spaces: str = field(default="own", metadata={"hash_if_set": True})   # ModelSettings.spaces, as `newlines`

    @classmethod
    def of(cls, direction: str, variant: str, mode: str, seed: int = 0, prompt: str = DEFAULT_PROMPT,
           step_headers: str = "numbered", numbers: str = "whole", plan_form: str = "moves",
           newlines: str = "own", spaces: str = "own") -> "TextSettings":
        # Direction-free variants (NONE, DFS): both directions share one dataset (and model). Step headers and
        # the Plan's anchors exist only where a Thought does (maps and CoT); the reachable mode has no Plan.
        if BY_NAME[variant].direction_free:
            step_headers, plan_form = "numbered", "moves"
        if mode != "optimal":
            plan_form = "moves"
        return cls(text_direction(direction, variant), variant, mode, seed, prompt, step_headers, numbers, plan_form,
                   newlines, spaces)


def world_file(data: DataSettings, split: str) -> ResolvedFile | None:
    """The file the ``split`` comes from (``data.test_file`` / ``data.train_file``), resolved: ``paper`` is the
    paper's released file (see `paper_data.resolve`); None: the split is generated."""
    value = data.test_file if split == "test" else data.train_file
    if not value:
        return None
    if value == PAPER_WORD:
        return resolve(split)
    path = Path(value).expanduser()
    if not path.is_file():
        raise FileNotFoundError(f"data.{split}_file={value!r}: no such file; expected a JSONL of worlds in the paper's "
                                f"schema (one {{\"question\": {{...}}}} per line), or 'paper'")
    return ResolvedFile(path, file_sha256(path), "explicit", False)


def world_files(data: DataSettings) -> dict[str, ResolvedFile | None]:
    """Both splits' files, resolved once (each resolution hashes its file)."""
    return {split: world_file(data, split) for split in ("train", "test")}


def repeated_worlds(worlds: list[World]) -> list[tuple[int, int]]:
    """(line, line of its first occurrence), 1-based, of every world that repeats an earlier one."""
    first: dict[tuple, int] = {}
    repeats = []
    for line, world in enumerate(worlds, 1):
        key = world.key()
        if key in first:
            repeats.append((line, first[key]))
        else:
            first[key] = line
    return repeats


def repeated_worlds_error(setting: str, worlds: list[World]) -> str | None:
    """The message refusing a split that holds a world twice (its episodes would count twice and its
    intervals shrink for nothing); None when every world is distinct."""
    repeats = repeated_worlds(worlds)
    if not repeats:
        return None
    shown = ", ".join(f"line {line} repeats line {earlier}" for line, earlier in repeats[:5])
    return (f"{setting}: {len(repeats)} world(s) repeat an earlier one ({shown}{', ...' if len(repeats) > 5 else ''}); "
            "allowed: a file of distinct worlds (drop the repeated lines)")


def _from_file(data: DataSettings, split: str, found: ResolvedFile | None) -> list[World] | None:
    n = data.n_test if split == "test" else data.n_train
    if found is None:
        return None
    worlds = load_worlds(found.path)
    if len(worlds) < n:
        raise ValueError(f"data.n_{split}={n} but data.{split}_file={str(found.path)!r} holds {len(worlds)} worlds; "
                         f"allowed: 1..{len(worlds)}")
    error = repeated_worlds_error(f"data.{split}_file={str(found.path)!r}", worlds[:n]) if split == "test" else None
    if error:
        raise ValueError(error)
    return worlds[:n]


def build_splits(data: DataSettings, files: dict[str, ResolvedFile | None] | None = None
                 ) -> tuple[list[World], list[World]]:
    """(train, test) worlds for a data config: each split generated or taken from its file (``files``: already
    resolved by `world_files`); a generated train split is disjoint from the test split."""
    files = world_files(data) if files is None else files
    test = _from_file(data, "test", files["test"])
    if test is None:
        test = generate_worlds(data.n_test, data.seed, data.generator_config("test"), split="test", workers=data.workers)
    train = _from_file(data, "train", files["train"])
    if train is None:
        exclude = frozenset(world.key() for world in test)
        train = generate_worlds(data.n_train, data.seed, data.generator_config("train"), split="train", exclude=exclude,
                                workers=data.workers)
    return train, test


VALID_SPLIT = "valid"


def validation_worlds(data: DataSettings, n: int, train: list[World], test: list[World]) -> list[World]:
    """The validation split: ``n`` worlds drawn as generated test worlds are (the test sizes, frame and
    generator, ``data.seed``) from a stream of their own, and disjoint from both ``train`` and ``test``. Recipes
    are chosen on it; the test split is then read once per final setting."""
    exclude = frozenset(world.key() for world in (*train, *test))
    return generate_worlds(n, data.seed, data.generator_config("test"), split=VALID_SPLIT, exclude=exclude,
                           workers=data.workers)


def _write_jsonl(path: Path, rows: Iterable[dict]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as handle:
        for row in rows:
            handle.write(json.dumps(row, separators=(", ", ": ")) + "\n")


def _conversations(worlds: list[World], spec: TextSettings, desc: str, distractors: int = 0, frame: int = 0,
                   mask_edge: tuple[int, int] | None = None) -> Iterable[dict]:
    """Each world's conversation; with ``mask_edge`` (the largest train sides) the first answer's edge labels
    (`edge_label_spans`) are listed under `UNTRAINED`."""
    direction = spec.direction or "fwd"
    for index, world in enumerate(tqdm(worlds, desc=desc, unit="world", leave=False)):
        # Each world's DFS walk gets its own seed, so the walks do not depend on the split's order.
        turns = conversation(world, direction, spec.variant, spec.mode, seed=spec.seed * 1_000_003 + index,
                             prompt=spec.prompt, steps=spec.step_headers,
                             obstacles=listed_obstacles(world, distractors, frame), plan=spec.plan_form)
        if mask_edge is not None:
            answer = next(turn for turn in turns if turn["from"] == "gpt")
            answer[UNTRAINED] = [list(span) for span in edge_label_spans(world, answer["value"], mask_edge)]
        yield {"id": index, "conversations": turns}


def _summary(values: list[int]) -> dict:
    return {"mean": statistics.fmean(values), "max": max(values), "min": min(values)} if values else {}


def write_dataset(out_dir: str | Path, train: list[World], test: list[World], spec: TextSettings,
                  train_max: tuple[int, int], distractors: int = 0, frame: int = 0, mask_edge: bool = False) -> dict:
    """Write worlds, conversations and stats under ``out_dir``; return the summary (also written).
    ``distractors``, ``frame``: the train prompts' extra obstacle-list cells (`DataSettings.train_distractors`);
    ``mask_edge``: the train answers' edge labels are no loss targets (`DataSettings.mask_edge_labels`)."""
    out = Path(out_dir)
    (out / "worlds").mkdir(parents=True, exist_ok=True)
    save_worlds(out / TRAIN_WORLDS, train)
    save_worlds(out / TEST_WORLDS, test)
    token_lengths: list[int] = []
    train_words: set[str] = set()
    untrained_labels = [0]
    test_words: list[frozenset[str]] = []

    def measured(rows: Iterable[dict]) -> Iterable[dict]:
        for row in rows:
            tokens = 0
            for turn in row["conversations"]:
                count, found = piece_census(turn["value"], spec.numbers, spec.newlines, spec.spaces)
                tokens += count + 2
                train_words.update(found)
                untrained_labels[0] += len(turn.get(UNTRAINED, ()))
            token_lengths.append(tokens)
            yield row

    def words_of(rows: Iterable[dict]) -> Iterable[dict]:
        for row in rows:
            test_words.append(frozenset().union(*(piece_set(turn["value"], spec.numbers, spec.newlines, spec.spaces)
                                                  for turn in row["conversations"])))
            yield row

    train_rows = _conversations(train, spec, "train texts", distractors, frame, train_max if mask_edge else None)
    _write_jsonl(out / TRAIN_CONVERSATIONS, measured(train_rows))
    train_tokens = list(token_lengths)
    # Test conversations are the golden references (the model is prompted with their turns before the first answer).
    _write_jsonl(out / TEST_CONVERSATIONS, words_of(_conversations(test, spec, "test texts")))
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
        "untrained_words": untrained_words(train_words, test_words),
        "untrained_edge_labels": untrained_labels[0],
        "sha256": dataset_sha256(out),
    }
    (out / SUMMARY).write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    return summary


def untrained_words(train_words: set[str], test_words: list[frozenset[str]]) -> dict:
    """The words (word-level pieces: `pipeline.lm.tokenizer.pieces`) the test conversations hold and no training
    conversation does: a model trained from scratch has never trained their embeddings, so a test world that
    needs one fails by construction. ``words``: each such word and how many test worlds need it; ``n_worlds``:
    how many test worlds need at least one."""
    by_word: dict[str, list[int]] = {}
    for index, words in enumerate(test_words):
        for word in words - train_words:
            by_word.setdefault(word, []).append(index)
    needing = {i for indices in by_word.values() for i in indices}
    return {"words": {word: len(by_word[word]) for word in sorted(by_word)}, "n_words": len(by_word),
            "n_worlds": len(needing), "n_test": len(test_words)}


def untrained_words_line(found: dict) -> str | None:
    """The one line data-build prints when the test needs words training never shows (None when it does not)."""
    if not found["n_words"]:
        return None
    shown = sorted(found["words"].items(), key=lambda item: (-item[1], item[0]))
    names = ", ".join(f"{word!r} ({n})" for word, n in shown[:8]) + (", ..." if len(shown) > 8 else "")
    return (f"[data-build] {found['n_worlds']} of {found['n_test']} test worlds need words that no training "
            f"conversation holds ({found['n_words']} words, with the test worlds needing each: {names}); a model "
            "trained from scratch never trained them")


def dataset_sha256(out_dir: str | Path) -> str:
    """One hash over the dataset's data files (not the summary), in a fixed order."""
    digest = hashlib.sha256()
    for name in (TRAIN_WORLDS, TEST_WORLDS, TRAIN_CONVERSATIONS, TEST_CONVERSATIONS, TEST_STATS):
        digest.update(name.encode())
        digest.update((Path(out_dir) / name).read_bytes())
    return digest.hexdigest()


# ---------------------------------------------------------------------------------------------------- the step
def run_data_build(settings: DataSettings, texts: TextSettings, files: dict[str, ResolvedFile | None],
                   step_dir: Path) -> None:
    """The data-build step's body (inside its MLflow run): build, write and log the dataset. ``files``: the
    splits' files as `world_files` resolved them."""
    log_settings(asdict(settings), "data")
    for split, found in files.items():
        if found is not None:  # which file, exactly (the paper's train file has no published checksum)
            mlflow.set_tags({f"{split}_file": str(found.path), f"{split}_file_sha256": found.sha256})
    out = step_dir / "dataset"
    with bulk_building():  # tens of thousands of worlds and conversations
        train, test = build_splits(settings, files)
        summary = write_dataset(out, train, test, texts, settings.train_max, settings.train_distractors,
                                settings.frame, settings.mask_edge_labels)
    mlflow.set_tag("dataset_sha256", summary["sha256"])
    mlflow.log_metrics({
        "n_train": summary["n_train"], "n_test": summary["n_test"],
        "train_tokens_mean": summary["train_tokens"]["mean"], "train_tokens_max": summary["train_tokens"]["max"],
        "test_path_length_mean": summary["test_path_length"]["mean"],
        "test_up_right_only": summary["test_up_right_only"], "test_interpolated": summary["test_interpolated"],
        "untrained_words": summary["untrained_words"]["n_words"],
        "test_worlds_untrained_words": summary["untrained_words"]["n_worlds"],
        "untrained_edge_labels": summary["untrained_edge_labels"],
    })
    line = untrained_words_line(summary["untrained_words"])
    if line:
        print(line, flush=True)
    mlflow.log_artifacts(str(out))
    base = mlflow.get_artifact_uri()
    for artifact, split in ((TRAIN_CONVERSATIONS, "train"), (TEST_CONVERSATIONS, "test")):
        log_dataset(f"{base}/{artifact}", out / artifact, dataset_name(texts, split), split)


def dataset_name(texts: TextSettings, split: str) -> str:
    return "-".join(p for p in (texts.direction, texts.variant, texts.mode, split) if p)


def log_step_dataset(data: StepRun, texts: TextSettings, artifact: str, split: str, context: str) -> None:
    """Log one of a data-build run's conversation files as a dataset input of the active run."""
    uri = f"{mlflow.get_run(data.run_id).info.artifact_uri}/{artifact}"
    log_dataset(uri, Path(data.artifact(artifact)), dataset_name(texts, split), context)
