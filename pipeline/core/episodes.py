"""The scored episode: one test world's result, exactly as a line of the eval step's ``episodes.jsonl``.

`ScoredEpisode.to_dict()` IS that file's schema (`EPISODE_FIELDS`): the world's statistics (`WorldStats`)
are written flat, right after its index. The eval step writes those dicts and the report and
``python -m pipeline.inspect`` read them back. Optimal-setting-only fields are null in the reachable setting.
`metrics` computes the eval run's metrics (`EVAL_METRICS`) from records alone.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from typing import Callable, Mapping, Sequence

from pipeline.core.environment import Outcome
from pipeline.core.generators.stats import WorldStats
from pipeline.core.map_errors import first_wrong_line
from pipeline.core.scoring import score_optimal
from pipeline.core.world import World

# The test world's statistics every record carries, as the first fields after its index.
STAT_FIELDS = tuple(f.name for f in fields(WorldStats))


@dataclass
class ScoredEpisode:
    world_index: int            # index in the test split
    stats: WorldStats           # written flat: its fields follow world_index
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
        """The episodes.jsonl line: the fields in order, the world's statistics flat in place of ``stats``."""
        row = asdict(self)
        return {"world_index": row.pop("world_index"), **row.pop("stats"), **row}


EPISODE_FIELDS: tuple[str, ...] = tuple(
    name for f in fields(ScoredEpisode) for name in (STAT_FIELDS if f.name == "stats" else (f.name,))
)


def _world_stats(stats: Mapping) -> WorldStats:
    # The stats arrive as a row of the data-build's stats file (a dict with WorldStats' fields).
    return WorldStats(**{name: stats[name] for name in STAT_FIELDS})


def optimal_episode(index: int, world: World, stats: Mapping, text: str, error: str | None, direction: str,
                    variant: str, steps: str = "numbered", plan: str = "moves") -> ScoredEpisode:
    """Score one single-turn answer (graded); ``stats``: the world's `WorldStats` fields; ``error``: the answer
    could not be generated. ``steps`` and ``plan``: how the golden answer writes its step headers
    (`texts.STEP_HEADERS`) and its Plan (`texts.PLAN_FORMS`)."""
    if error is not None:
        return ScoredEpisode(index, _world_stats(stats), success=False, outcome="error", n_moves=0, parsed=False,
                             valid=False, reaches_goal=False, answers=[text], error=error)
    score = score_optimal(world, text, direction, variant, steps, plan)
    wrong = first_wrong_line(world, direction, variant, text, steps, plan)
    return ScoredEpisode(
        index, _world_stats(stats), success=bool(score.optimal), outcome="success" if score.optimal else "fail",
        n_moves=len(score.moves), moves=list(score.moves), parsed=score.parsed, valid=score.valid,
        reaches_goal=score.reaches_goal, map_exact=score.map_exact, map_first_error=score.map_first_error,
        first_wrong_line=wrong.to_dict() if wrong is not None else None, answers=[text],
    )


def reachable_episode(index: int, stats: Mapping, outcome: str | None, moves: Sequence[str], error: str | None,
                      answers: Sequence[str] = ()) -> ScoredEpisode:
    """Record one multi-turn episode with the model's answer of every turn; ``stats``: the world's `WorldStats`
    fields."""
    return ScoredEpisode(index, _world_stats(stats), success=outcome == Outcome.SUCCESS.value and error is None,
                         outcome="error" if error is not None else outcome, n_moves=len(moves), moves=list(moves),
                         answers=list(answers), error=error)


Predicate = Callable[[dict], bool]


def _every(record: dict) -> bool:
    return True


def _outcome_is(outcome: str) -> Predicate:
    return lambda record: record["outcome"] == outcome


def _graded(name: str) -> Predicate:
    return lambda record: record[name] is not None


def _holds(name: str) -> Predicate:
    return lambda record: bool(record[name])


# Each rate metric: (the records it is a rate over, what it counts among them). THE list of metrics, in the
# order `metrics` returns them.
_RATES: dict[str, tuple[Predicate, Predicate]] = {
    "success_rate": (_every, _holds("success")),
    "success_rate_interp": (_holds("interpolated"), _holds("success")),
    "success_rate_extrap": (lambda record: not record["interpolated"], _holds("success")),
    "rate_error": (_every, _outcome_is("error")),
    **{f"rate_{o.value}": (_every, _outcome_is(o.value)) for o in (Outcome.DEADEND, Outcome.MAX_STEP, Outcome.INVALID)},
    # The optimal setting's grades, over the records graded (null in the reachable setting).
    **{f"rate_{name}": (_graded(name), _holds(name)) for name in ("parsed", "valid", "reaches_goal", "map_exact")},
}

# Every metric the eval run may log: the episode count, then the rates.
EVAL_METRICS: tuple[str, ...] = ("n_episodes", *_RATES)


def metrics(records: list[dict]) -> dict[str, float]:
    """The eval run's metrics (`EVAL_METRICS`); rates over empty subsets are left out."""
    values = {"n_episodes": float(len(records))}
    for name, (over, counted) in _RATES.items():
        subset = [record for record in records if over(record)]
        if subset:
            values[name] = sum(1 for record in subset if counted(record)) / len(subset)
    return values
