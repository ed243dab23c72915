"""The eval step: prompt the finetuned model with each test world, score what it does, keep one record
(`pipeline.core.episodes.ScoredEpisode`) per episode, and log them with their metrics.

Records are appended to a partial file as episodes finish, so an interrupted eval resumes from its
completed episodes; the finished eval orders them by world index. Metrics are computed from the records
alone (the report recomputes its splits from the same records).
"""

from __future__ import annotations

import functools
import json
import os
import signal
import sys
import traceback
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Optional

import mlflow
from tqdm import tqdm

from pipeline.core.checks import SettingError, require
from pipeline.core.environment import RULES
from pipeline.core.generators import world_stats
from pipeline.core.episodes import metrics, optimal_episode, reachable_episode
from pipeline.core.texts import DEFAULT_PROMPT, prompt_turns
from pipeline.core.world import World, load_worlds
from pipeline.lm.decoding import BACKENDS, Decoder, make_decoder
from pipeline.lm.model_settings import ModelSettings
from pipeline.workflow.data_build import (
    TEST_CONVERSATIONS, TEST_STATS, TEST_WORLDS, TRAIN_WORLDS, DataSettings, TextSettings, log_step_dataset,
    validation_worlds,
)
from pipeline.workflow.steps import StepRun
from pipeline.workflow.tracking import (
    CHECKPOINTS_ARTIFACT, CURVE_EPISODES_ARTIFACT, CURVE_METRIC, EPISODES_ARTIFACT, VALID_EPISODES_ARTIFACT, VALID_PREFIX,
)


@dataclass
class EvalSettings:
    """How the eval step decodes and scores. ``max_moves``: a reachable episode ends MAX STEP after this many
    moves. ``curve``: also evaluate each logged checkpoint on the first ``curve_worlds`` test worlds (the
    paper's Figure 3). The defaults are the base of the ``conf/eval`` presets."""

    n_worlds: Optional[int] = None      # the first n test worlds; null: all
    backend: str = "hf"                 # hf | vllm
    batch_size: int = 32
    max_new_tokens: int = 4096
    max_moves: int = 200
    # How reachable episodes are judged: "project" (ours) or "paper" (the paper's harness: a goal reached on
    # the max_moves-th answer fails, an empty answer is MAX STEP, the move is everything after "Action:\n").
    rules: str = "project"
    curve: bool = False
    curve_worlds: int = 50
    # Also score this many validation worlds (`data_build.validation_worlds`: the test distribution, disjoint
    # from train and test), logged as valid_* metrics and episodes_valid.jsonl: choose recipes on these.
    n_valid: int = field(default=0, metadata={"hash_if_set": True})
    # With ``curve``: also score every logged checkpoint on all ``n_valid`` validation worlds (valid_curve_*
    # metrics by training step): choose a checkpoint or a budget on these, not on the test curve.
    curve_valid: bool = field(default=False, metadata={"hash_if_set": True})

    def __post_init__(self) -> None:
        require(self.backend in BACKENDS, "backend", self.backend, f"one of {', '.join(BACKENDS)}")
        require(self.rules in RULES, "rules", self.rules, f"one of {', '.join(RULES)}")
        require(self.n_worlds is None or self.n_worlds >= 1, "n_worlds", self.n_worlds, "at least 1, or null for all")
        for name in ("batch_size", "max_new_tokens", "max_moves", "curve_worlds"):
            require(getattr(self, name) >= 1, name, getattr(self, name), "at least 1")
        require(self.n_valid >= 0, "n_valid", self.n_valid, "0 (no validation split) or more")
        require(not self.curve_valid or (self.curve and self.n_valid > 0), "curve_valid", self.curve_valid,
                "false, or true with curve=true and n_valid >= 1 (it scores the curve's checkpoints on the validation worlds)")


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
    max_moves: int,
    partial_path: str | Path,
    chunk_size: int = 64,
    prompt: str = DEFAULT_PROMPT,
    rules: str = "project",
    steps: str = "numbered",
    plan: str = "moves",
    show_progress: bool = True,
) -> list[dict]:
    """Run every world not yet in ``partial_path`` and return all records in world order.

    Chunks are fixed blocks of world indices, so a resumed eval batches the worlds it still has to do
    exactly as an uninterrupted one would (optimal-setting records are written a whole chunk at a time,
    so its finished chunks are skipped whole and the rest decode in the very same batches).
    """
    partial = PartialRecords(partial_path)
    done = sum(1 for i in range(len(worlds)) if i in partial.records)
    progress = tqdm(total=len(worlds), initial=done, desc=f"eval {mode}", unit="world",
                    disable=not show_progress)
    try:
        for start in range(0, len(worlds), chunk_size):
            chunk = [i for i in range(start, min(start + chunk_size, len(worlds))) if i not in partial.records]
            if not chunk:
                continue
            if mode == "optimal":
                generations = decoder.generate([prompt_turns(worlds[i], prompt) for i in chunk])
                for i, generation in zip(chunk, generations):
                    partial.add(optimal_episode(i, worlds[i], stats[i], generation.text, generation.error, direction, variant,
                                              steps, plan).to_dict())
                    progress.update()
            else:
                def finished(episode, chunk=chunk) -> None:
                    i = chunk[episode.world_index]
                    outcome = episode.outcome.value if episode.outcome is not None else None
                    partial.add(reachable_episode(i, stats[i], outcome, episode.moves, episode.error, episode.answers).to_dict())
                    progress.update()

                decoder.play([worlds[i] for i in chunk], max_moves=max_moves, on_episode=finished, prompt=prompt, rules=rules)
    finally:
        progress.close()
        partial.close()
    return partial.ordered()


def run_eval(settings: EvalSettings, model: ModelSettings, texts: TextSettings, data: StepRun, finetune: StepRun,
             step_dir: Path, data_settings: DataSettings) -> None:
    """The eval step's body (inside its MLflow run): decode, score, and log episodes and metrics; with
    ``settings.n_valid``, the validation worlds too (``data_settings``: the job's, which they are drawn from)."""
    log_step_dataset(data, texts, TEST_CONVERSATIONS, "test", "evaluation")
    worlds = load_worlds(data.artifact(TEST_WORLDS))
    stats = [json.loads(line) for line in Path(data.artifact(TEST_STATS)).read_text().splitlines()]
    n = settings.n_worlds or len(worlds)
    if n > len(worlds):
        raise SettingError(f"eval.n_worlds={n} but the test split has {len(worlds)} worlds; allowed: 1..{len(worlds)} or null")
    # Local paths, found through the store here: a forked copy of this process must not touch the store.
    model_dir = finetune.artifact("model")
    train_worlds = data.artifact(TRAIN_WORLDS) if settings.n_valid else None
    validate = functools.partial(_evaluate_validation, settings, model, texts, model_dir, train_worlds, worlds,
                                 data_settings, step_dir)
    # The validation worlds decoded in a process of its own meanwhile, where that can be (`_decoded_beside`); their
    # records then wait in their partial file, and `validate` below only reads them.
    split = None
    with _decoded_beside(validate if settings.n_valid and settings.backend == "hf" else None):
        records = _evaluate_model(settings, model, texts, model_dir, worlds[:n], stats[:n],
                                  step_dir / "episodes.partial.jsonl")
        if settings.n_valid:
            split = _validation_split(settings, train_worlds, worlds, data_settings)
    episodes = step_dir / EPISODES_ARTIFACT
    episodes.write_text("".join(json.dumps(record) + "\n" for record in records))
    mlflow.log_artifact(str(episodes))
    mlflow.log_metrics(metrics(records))
    valid = validate(split=split) if settings.n_valid else None
    if settings.curve:
        n = min(settings.curve_worlds, len(worlds))
        curves = {"": (worlds[:n], stats[:n]), **({VALID_PREFIX: valid} if settings.curve_valid else {})}
        _evaluate_curve(settings, model, texts, finetune, curves, step_dir)


def _validation_split(settings: EvalSettings, train_worlds: str, test: list[World], data_settings: DataSettings
                      ) -> tuple[list[World], list[dict]]:
    """The validation worlds (`data_build.validation_worlds`; ``train_worlds``: the train split's file) and their
    stats."""
    train = load_worlds(train_worlds)
    worlds = validation_worlds(data_settings, settings.n_valid, train, test)
    return worlds, [asdict(world_stats(world, data_settings.train_max)) for world in worlds]


def _evaluate_validation(settings: EvalSettings, model: ModelSettings, texts: TextSettings, model_dir: str,
                         train_worlds: str, test: list[World], data_settings: DataSettings, step_dir: Path,
                         log: bool = True, split: tuple[list[World], list[dict]] | None = None
                         ) -> tuple[list[World], list[dict]]:
    """Score the validation worlds (``split``, else `_validation_split`'s) with the model at ``model_dir``, logged as
    valid_* metrics unless ``log`` is false (their records are then only written to their partial file); returns
    them and their stats."""
    worlds, stats = split or _validation_split(settings, train_worlds, test, data_settings)
    records = _evaluate_model(settings, model, texts, model_dir, worlds, stats,
                              step_dir / "episodes_valid.partial.jsonl", show_progress=log)
    if not log:
        return worlds, stats
    episodes = step_dir / VALID_EPISODES_ARTIFACT
    episodes.write_text("".join(json.dumps(record) + "\n" for record in records))
    mlflow.log_artifact(str(episodes))
    mlflow.log_metrics({VALID_PREFIX + key: value for key, value in metrics(records).items()})
    return worlds, stats


@contextmanager
def _decoded_beside(work: Callable[..., object] | None):
    """Run ``work(log=False)`` in a forked copy of this process while the block runs here, each on one torch thread
    (a decoding's small matmuls gain little from a second thread: 0.88x the time; two decodings side by side use
    both cores), then wait for it. Only with ``work``, ``os.fork``, no GPU and at least two torch threads; otherwise
    nothing runs beside. The copy writes nothing but what ``work`` writes (its partial records) and ends without
    Python's exit; whatever it left undone (it failed, or was stopped) the caller's own ``work()`` does after: a
    resumed eval. The same texts either way (decoding on one thread or two, checked on the default job's worlds)."""
    import torch

    threads = torch.get_num_threads()
    if work is None or not hasattr(os, "fork") or torch.cuda.is_available() or threads < 2:
        yield
        return
    sys.stdout.flush()
    sys.stderr.flush()
    parent = os.getpid()
    child = os.fork()
    if child == 0:  # the copy: only the forking thread lives here; no MLflow, no bars, no exit handlers
        status = 1
        try:
            _end_with_parent(parent)
            torch.set_num_threads(1)
            work(log=False)
            status = 0
        except BaseException:  # noqa: BLE001 - the caller redoes what is missing and meets the error itself
            traceback.print_exc()
        finally:
            sys.stderr.flush()
            os._exit(status)
    torch.set_num_threads(1)
    try:
        yield
        os.waitpid(child, 0)
        child = 0
    finally:
        torch.set_num_threads(threads)
        if child:  # the block failed or was stopped: the copy's work is no longer wanted
            os.kill(child, signal.SIGKILL)
            os.waitpid(child, 0)


def _end_with_parent(parent: int) -> None:
    """Have the kernel end this process when its parent ends (Linux), so a job killed outright leaves no copy
    writing to its partial records; ends it now if the parent is gone already."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() != parent:
        os._exit(1)


def _evaluate_model(settings: EvalSettings, model: ModelSettings, texts: TextSettings, model_dir: str,
                    worlds: list[World], stats: list[dict], partial_path: Path, show_progress: bool = True
                    ) -> list[dict]:
    decoder = make_decoder(model_dir, backend=settings.backend, batch_size=settings.batch_size,
                           max_new_tokens=settings.max_new_tokens, dtype=model.dtype,
                           trust_remote_code=model.trust_remote_code, attn_implementation=model.attn_implementation)
    return evaluate(decoder, worlds, stats, mode=texts.mode, direction=texts.direction or "fwd", variant=texts.variant,
                    max_moves=settings.max_moves, partial_path=partial_path, prompt=texts.prompt, rules=settings.rules,
                    steps=texts.step_headers, plan=texts.plan_form, show_progress=show_progress)


# The curve's rates (`metrics`' names) and the suffix each is logged with after the curve's metric name.
_CURVE_RATES = {"success_rate": "", "success_rate_interp": "_interp", "success_rate_extrap": "_extrap"}


def _evaluate_curve(settings: EvalSettings, model: ModelSettings, texts: TextSettings, finetune: StepRun,
                    curves: dict[str, tuple[list[World], list[dict]]], step_dir: Path) -> None:
    """Figure 3: success of every logged checkpoint on each curve's worlds (``curves``: metric prefix -> worlds
    and stats; "" the first ``curve_worlds`` test worlds, `VALID_PREFIX` the validation worlds), by training step."""
    entries = mlflow.artifacts.list_artifacts(run_id=finetune.run_id, artifact_path=CHECKPOINTS_ARTIFACT)
    train_steps = sorted(int(Path(entry.path).name.split("-")[-1]) for entry in entries if entry.is_dir)
    for train_step in train_steps:
        model_dir = finetune.artifact(f"{CHECKPOINTS_ARTIFACT}/step-{train_step}")
        for prefix, (worlds, stats) in curves.items():
            records = _evaluate_model(settings, model, texts, model_dir, worlds, stats,
                                      step_dir / f"{prefix}curve-{train_step}.partial.jsonl")
            rates = metrics(records)
            mlflow.log_metrics({prefix + CURVE_METRIC + suffix: rates[key] for key, suffix in _CURVE_RATES.items()
                                if key in rates}, step=train_step)
            episodes = step_dir / f"{prefix}curve" / f"step-{train_step}.jsonl"
            episodes.parent.mkdir(parents=True, exist_ok=True)
            episodes.write_text("".join(json.dumps(record) + "\n" for record in records))
            mlflow.log_artifact(str(episodes), prefix + CURVE_EPISODES_ARTIFACT)
