"""The episode record: one test world's result, exactly as a line of the eval step's ``episodes.jsonl``.

`Episode` IS that file's schema (`EPISODE_FIELDS`); the eval step writes ``Episode.to_dict()`` and the
report and ``python -m pipeline.inspect`` read those dicts back. Optimal-setting-only fields are null in the
reachable setting. `metrics` computes the eval run's metrics from records alone.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Iterable, Sequence

from pipeline.core.environment import Outcome
from pipeline.core.generation import WorldStats
from pipeline.core.map_errors import first_wrong_line
from pipeline.core.scoring import score_optimal
from pipeline.core.world import World

# The test world's statistics every record carries, as the first fields after its index.
STAT_FIELDS = tuple(f.name for f in fields(WorldStats))


@dataclass
class Episode:
    world_index: int            # index in the test split
    size_x: int
    size_y: int
    optimal_length: int
    dead_ends: int
    up_right_only: bool
    interpolated: bool
    success: bool               # SUCCESS in either setting
    outcome: str                # reachable: success|deadend|max_step|invalid; optimal: success|fail; or error
    n_moves: int                # moves taken (reachable) or planned (optimal)
    moves: list[str] = field(default_factory=list)
    parsed: bool | None = None  # optimal setting, graded: the answer parsed ...
    valid: bool | None = None   # ... its plan stayed on free cells ...
    reaches_goal: bool | None = None  # ... and reached the goal
    map_exact: bool | None = None     # the Thought section equals the golden one (maps only)
    map_first_error: int | None = None  # first differing line of the answer (0-based), when not exact
    first_wrong_line: dict | None = None  # map_errors.ErrorSite of the first wrong line; null when all are right
    answers: list[str] = field(default_factory=list)  # the model's raw answers: one (optimal) or one per turn
    error: str | None = None    # why this single episode could not run (e.g. a prompt longer than the context)

    def to_dict(self) -> dict:
        return asdict(self)


EPISODE_FIELDS: tuple[str, ...] = tuple(f.name for f in fields(Episode))


def _stats(index: int, stats: dict) -> dict:
    return {"world_index": index, **{key: stats[key] for key in STAT_FIELDS}}


def optimal_episode(index: int, world: World, stats: dict, text: str, error: str | None, direction: str,
                    variant: str, steps: str = "numbered") -> Episode:
    """Score one single-turn answer (graded); ``error``: the answer could not be generated. ``steps``: how the
    golden map writes its step headers (`texts.STEP_HEADERS`)."""
    if error is not None:
        return Episode(**_stats(index, stats), success=False, outcome="error", n_moves=0, parsed=False, valid=False,
                       reaches_goal=False, answers=[text], error=error)
    score = score_optimal(world, text, direction, variant, steps)
    wrong = first_wrong_line(world, direction, variant, text, steps)
    return Episode(
        **_stats(index, stats), success=bool(score.optimal), outcome="success" if score.optimal else "fail",
        n_moves=len(score.moves), moves=list(score.moves), parsed=score.parsed, valid=score.valid,
        reaches_goal=score.reaches_goal, map_exact=score.map_exact, map_first_error=score.map_first_error,
        first_wrong_line=wrong.to_dict() if wrong is not None else None, answers=[text],
    )


def reachable_episode(index: int, stats: dict, outcome: str | None, moves: Sequence[str], error: str | None,
                      answers: Sequence[str] = ()) -> Episode:
    """Record one multi-turn episode with the model's answer of every turn."""
    return Episode(**_stats(index, stats), success=outcome == Outcome.SUCCESS.value and error is None,
                   outcome="error" if error is not None else outcome, n_moves=len(moves), moves=list(moves),
                   answers=list(answers), error=error)


def _rate(records: Iterable[dict], predicate) -> float | None:
    records = list(records)
    return sum(1 for r in records if predicate(r)) / len(records) if records else None


def metrics(records: list[dict]) -> dict[str, float]:
    """The eval run's metrics (`EVAL_METRICS`); rates over empty subsets are left out."""
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
    for name in ("parsed", "valid", "reaches_goal", "map_exact"):
        graded = [r for r in records if r[name] is not None]
        if graded:
            values[f"rate_{name}"] = _rate(graded, lambda r, f=name: bool(r[f]))
    return {key: value for key, value in values.items() if value is not None}


EVAL_METRICS = (
    "success_rate", "success_rate_interp", "success_rate_extrap", "n_episodes",
    "rate_deadend", "rate_max_step", "rate_invalid", "rate_error",      # reachable outcomes
    "rate_parsed", "rate_valid", "rate_reaches_goal", "rate_map_exact",  # optimal, graded
)
