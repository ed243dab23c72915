"""Parsing model answers and grading optimal-setting plans (docs/spec.md §4). Nothing here raises on model text."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.core.texts import golden_answer, parse_cell, thought_lines
from pipeline.core.variants import MAP_VARIANTS
from pipeline.core.world import MOVES, World, step

_HEADERS = ("Thought:", "Backtrack:", "Plan:", "Action:")


@dataclass
class ParsedAnswer:
    """The sections of an answer; a section that is absent is None (an empty one is [])."""

    thought: list[str] | None = None
    backtrack: list[str] | None = None
    plan: list[str] | None = None
    action: str | None = None


def _as_text(text: object) -> str:
    """Whatever a decoder handed back, as a str (None and bytes included)."""
    if text is None:
        return ""
    if isinstance(text, bytes):
        return text.decode("utf-8", errors="replace")
    return text if isinstance(text, str) else str(text)


def parse_answer(text: object) -> ParsedAnswer:
    """Split an answer into Thought (map lines), Backtrack, Plan (raw lines) and Action (one line).

    Section headers are whole lines (surrounding whitespace ignored); a section runs to the next header.
    The first occurrence of a header wins, so a rambling model cannot overwrite an earlier section.
    """
    sections: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in _as_text(text).split("\n"):
        header = line.strip()
        if header in _HEADERS:
            current = None if header in sections else sections.setdefault(header, [])
        elif current is not None:
            current.append(line)
    action_lines = sections.get("Action:")
    return ParsedAnswer(
        thought=sections.get("Thought:"),
        backtrack=sections.get("Backtrack:"),
        plan=sections.get("Plan:"),
        action=action_lines[0].strip() if action_lines else None,
    )


def parse_action_paper(text: object) -> str | None:
    """The move as the paper's harness reads it: everything after the first ``Plan:\n`` (else after the first
    ``Action:\n``), up to a second one, with ``<think>`` removed; else the bare answer. None unless that is
    exactly a move (so ``Action:\nup\n`` or a trailing space is not one)."""
    text = _as_text(text)
    for header in ("Plan:\n", "Action:\n"):
        if header in text:
            text = text.split(header)[1].replace("<think>", "")
            break
    return text if text in MOVES else None


def parse_action(text: object) -> str | None:
    """The move of a reachable answer: the line after `Action:`, else the bare text; None if not a move."""
    text = _as_text(text)
    action = parse_answer(text).action
    candidate = action if action is not None else text.strip()
    return candidate if candidate in MOVES else None


@dataclass
class PlanScore:
    """Graded result of one optimal-setting answer (searchformer-style: parsed, valid, reaches, optimal)."""

    parsed: bool
    valid: bool
    reaches_goal: bool
    optimal: bool
    map_exact: bool | None
    map_first_error: int | None
    plan_length: int | None
    optimal_length: int
    moves: tuple[str, ...] = ()      # the parsed plan (empty when it does not parse)


def plan_moves(parsed: ParsedAnswer, plan: str = "moves") -> list[str] | None:
    """The Plan section as moves (blank lines ignored), or None if absent or not all moves. ``plan="anchored"``
    (`texts.PLAN_FORMS`): cell lines are read past, so only the moves are graded (a wrong anchor is a map
    error, not a plan error)."""
    if parsed.plan is None:
        return None
    moves = [line.strip() for line in parsed.plan if line.strip()]
    if plan == "anchored":
        moves = [line for line in moves if parse_cell(line) is None]
    return moves if moves and all(m in MOVES for m in moves) else None


def _walk(world: World, moves: list[str]) -> tuple[bool, bool]:
    """(valid, reaches_goal): valid if no move leaves the grid or enters an obstacle."""
    cell = world.start
    for move in moves:
        cell = step(cell, move)
        if not world.is_free(cell):
            return False, False
    return True, cell == world.goal


def first_difference(produced: list[str], golden: list[str]) -> int | None:
    """Index of the first line where `produced` departs from `golden` (a length mismatch counts), or None."""
    for i, (a, b) in enumerate(zip(produced, golden)):
        if a != b:
            return i
    return None if len(produced) == len(golden) else min(len(produced), len(golden))


def score_optimal(world: World, text: object, direction: str, variant: str, steps: str = "numbered",
                  plan: str = "moves") -> PlanScore:
    """Grade an optimal-setting answer against the world's unique shortest path and golden answer.

    `direction`, `variant` and `plan` are checked (ValueError names the allowed ones); the text never raises.
    """
    golden = golden_answer(world, direction, variant, "optimal", steps=steps, plan=plan)
    parsed = parse_answer(text)
    moves = plan_moves(parsed, plan)
    valid, reaches = _walk(world, moves) if moves is not None else (False, False)
    optimal_moves = world.optimal_moves()
    map_exact = None
    if variant in MAP_VARIANTS:
        # thought_lines includes the "Thought:" header, which the parser strips.
        map_exact = parsed.thought is not None and _thought_of(world, direction, variant, steps) == parsed.thought
    return PlanScore(
        parsed=moves is not None,
        valid=valid,
        reaches_goal=reaches,
        optimal=moves == optimal_moves,
        map_exact=map_exact,
        map_first_error=first_difference(_as_text(text).split("\n"), golden.split("\n")),
        plan_length=len(moves) if moves is not None else None,
        optimal_length=len(optimal_moves),
        moves=tuple(moves or ()),
    )


def _thought_of(world: World, direction: str, variant: str, steps: str) -> list[str]:
    """The golden Thought section as the parser returns it: map lines up to Backtrack, no header."""
    lines = thought_lines(world, direction, variant, steps)[1:]
    return lines[: lines.index("Backtrack:")] if "Backtrack:" in lines else lines
