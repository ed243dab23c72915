"""The reachable-setting environment: one world, moves in, observations and outcomes out (docs/spec.md §4)."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from enum import Enum

from pipeline.core.texts import first_human_text, observation
from pipeline.core.world import MOVES, Cell, World, step


# How an episode is judged: ours, or the paper's harness (see GridEnv).
RULES = ("project", "paper")


class Outcome(str, Enum):
    """How an episode ended."""

    SUCCESS = "success"
    DEADEND = "deadend"
    MAX_STEP = "max_step"
    INVALID = "invalid"


@dataclass(frozen=True)
class StepResult:
    """What one move produced: the next observation while the episode goes on, else the outcome."""

    observation: str | None
    done: bool
    outcome: Outcome | None


@dataclass
class EpisodeTranscript:
    """What the environment saw of one played (finished or cut-off) episode: the moves and how it ended, flat
    enough for a table row."""

    outcome: Outcome | None
    moves: list[str]
    n_moves: int
    optimal_length: int
    size_x: int
    size_y: int
    final_position: Cell
    invalid_answer: str | None = None

    def to_dict(self) -> dict:
        """Plain JSON-ready dict (outcome as its string value, cells as lists)."""
        row = asdict(self)
        row["outcome"] = self.outcome.value if self.outcome else None
        row["final_position"] = list(self.final_position)
        return row


@dataclass
class GridEnv:
    """Walks one world. `reset()` gives the third human turn; each `step(move)` the next observation.

    An episode ends with SUCCESS on the goal, DEADEND on a move outside the grid or into a wall or pit,
    INVALID on an answer that is not a move, and MAX_STEP once `max_moves` moves have not reached the
    goal (so the model is never asked for move max_moves + 1, which would be "more than" the limit).

    ``rules="paper"`` judges as the paper's harness does: the answer that reaches the limit ends MAX_STEP
    whatever it does (a goal reached on the 200th answer is a failure there), and so does an empty answer
    (`step`'s ``answer``); the move is read by `scoring.parse_action_paper` (the caller's business).
    """

    world: World
    max_moves: int = 200
    rules: str = "project"
    position: Cell = field(init=False)
    moves: list[str] = field(init=False, default_factory=list)
    outcome: Outcome | None = field(init=False, default=None)
    invalid_answer: str | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        if self.max_moves < 1:
            raise ValueError(f"max_moves must be at least 1, got {self.max_moves}")
        if self.rules not in RULES:
            raise ValueError(f"rules={self.rules!r} is not allowed; expected one of {', '.join(RULES)}")
        self.position = self.world.start

    @property
    def done(self) -> bool:
        """Whether the episode has ended."""
        return self.outcome is not None

    def reset(self) -> str:
        """Start over at the start cell; returns the full third human turn (task text + observation)."""
        self.position = self.world.start
        self.moves = []
        self.outcome = None
        self.invalid_answer = None
        return first_human_text(self.world)

    def step(self, move: str | None, answer: str | None = None) -> StepResult:
        """Apply one move (or a non-move answer, which ends the episode as INVALID); ``answer`` is the raw
        answer the move was read from (the paper's rules end an empty one MAX_STEP)."""
        if self.done:
            raise RuntimeError(f"the episode is over ({self.outcome.value}); call reset() first")
        if self.rules == "paper" and (answer == "" or len(self.moves) + 1 >= self.max_moves):
            if move in MOVES:
                self.moves.append(move)
            return self._end(Outcome.MAX_STEP)
        if move not in MOVES:
            self.invalid_answer = move
            return self._end(Outcome.INVALID)
        self.moves.append(move)
        target = step(self.position, move)
        if not self.world.is_free(target):
            return self._end(Outcome.DEADEND)
        self.position = target
        if target == self.world.goal:
            return self._end(Outcome.SUCCESS)
        if len(self.moves) >= self.max_moves:
            return self._end(Outcome.MAX_STEP)
        return StepResult(observation=observation(self.world, target), done=False, outcome=None)

    def transcript(self) -> EpisodeTranscript:
        """The episode so far."""
        return EpisodeTranscript(
            outcome=self.outcome,
            moves=list(self.moves),
            n_moves=len(self.moves),
            optimal_length=len(self.world.shortest_path()) - 1,
            size_x=self.world.size_x,
            size_y=self.world.size_y,
            final_position=self.position,
            invalid_answer=self.invalid_answer,
        )

    def _end(self, outcome: Outcome) -> StepResult:
        self.outcome = outcome
        return StepResult(observation=None, done=True, outcome=outcome)
