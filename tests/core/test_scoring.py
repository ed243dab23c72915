"""Parsing and plan scoring: golden answers score optimal, graded failures, never a raise on any text."""

from __future__ import annotations

import pytest
from conftest import GOLDEN_FWD_MARKING_DEADEND, worlds
from hypothesis import given
from hypothesis import strategies as st

from pipeline import conversation
from pipeline.core.scoring import (
    ParsedAnswer,
    PlanScore,
    first_difference,
    parse_action,
    parse_answer,
    score_optimal,
)
from pipeline.core.texts import golden_answer
from pipeline.core.variants import DIRECTIONS, MAP_VARIANTS, MODES, VARIANTS
from pipeline.core.world import World

GOLDEN_LINES = GOLDEN_FWD_MARKING_DEADEND.split("\n")
# The worked example again, at module level: hypothesis tests cannot take function-scoped fixtures.
_EXAMPLE = World(4, 3, 0, 0, ((1, 1), (2, 2)), ((3, 0),), (0, 0), (3, 2))


def test_parse_golden_sections(golden):
    parsed = parse_answer(golden["bwd_no_all"])
    assert parsed.thought == [
        "Step 1:",
        "(3, 1)",
        "up",
        "Step 2:",
        "(2, 1)",
        "right",
        "Step 3:",
        "(2, 0)",
        "up",
        "Step 4:",
        "(1, 0)",
        "right",
        "Step 5:",
        "(0, 0)",
        "right",
    ]
    assert parsed.backtrack[:3] == ["(0, 0)", "right", "(1, 0)"] and parsed.backtrack[-1] == "(3, 2)"
    assert parsed.plan == ["right", "right", "up", "right", "up"]
    assert parsed.action is None


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("Plan:\nup", ParsedAnswer(plan=["up"])),
        ("Action:\n left ", ParsedAnswer(action="left")),
        ("Thought:\nStep 1:\nAction:\nup", ParsedAnswer(thought=["Step 1:"], action="up")),
        ("Thought:", ParsedAnswer(thought=[])),
        ("", ParsedAnswer()),
        (None, ParsedAnswer()),
        (b"Plan:\nup", ParsedAnswer(plan=["up"])),
        ("Plan:\nup\nPlan:\ndown", ParsedAnswer(plan=["up"])),
    ],
)
def test_parse_answer_cases(text, expected):
    assert parse_answer(text) == expected


@pytest.mark.parametrize(
    ("text", "move"),
    [
        ("Thought:\nStep 1:\nAction:\nright", "right"),
        ("Action:\nup", "up"),
        (" down\n", "down"),
        ("left", "left"),
        ("Action:\njump", None),
        ("Action:", None),
        ("upward", None),
        ("", None),
        (None, None),
    ],
)
def test_parse_action(text, move):
    assert parse_action(text) == move


def test_golden_answers_score_optimal(example_world, golden):
    score = score_optimal(example_world, golden["fwd_marking_deadend"], "fwd", "marking-deadend")
    assert score == PlanScore(
        parsed=True,
        valid=True,
        reaches_goal=True,
        optimal=True,
        map_exact=True,
        map_first_error=None,
        plan_length=5,
        optimal_length=5,
        moves=tuple(example_world.optimal_moves()),
    )
    assert score_optimal(example_world, golden["bwd_no_all"], "bwd", "no-all").optimal


def test_graded_failures(example_world):
    plan_head = "\n".join(GOLDEN_LINES[: GOLDEN_LINES.index("Plan:") + 1])
    # Valid but stops short.
    short = score_optimal(example_world, plan_head + "\nright\nright", "fwd", "marking-deadend")
    assert (short.parsed, short.valid, short.reaches_goal, short.optimal) == (True, True, False, False)
    assert short.map_exact and short.plan_length == 2
    # Walks into the pit at (3, 0).
    pit = score_optimal(example_world, plan_head + "\nright\nright\nright", "fwd", "marking-deadend")
    assert (pit.parsed, pit.valid, pit.reaches_goal) == (True, False, False)
    # Reaches the goal by a longer legal walk: not optimal.
    detour = score_optimal(example_world, "Plan:\nup\ndown\nright\nright\nup\nright\nup", "fwd", "none")
    assert (detour.valid, detour.reaches_goal, detour.optimal, detour.map_exact) == (True, True, False, None)
    assert detour.map_first_error == 1
    # A plan line that is not a move: not parsed.
    garbled = score_optimal(example_world, plan_head + "\nright\nnorth", "fwd", "marking-deadend")
    assert not garbled.parsed and garbled.plan_length is None and not garbled.optimal


def test_an_anchored_plan_is_graded_by_its_moves(example_world):
    anchored = golden_answer(example_world, "fwd", "marking-deadend", "optimal", plan="anchored")
    score = score_optimal(example_world, anchored, "fwd", "marking-deadend", plan="anchored")
    assert score.optimal and score.map_exact and score.map_first_error is None and score.plan_length == 5
    lines = anchored.split("\n")
    # A wrong anchor with the right moves: the plan is optimal, the answer departs from the golden one there.
    wrong = lines[:-1] + ["(3, 3)"]
    score = score_optimal(example_world, "\n".join(wrong), "fwd", "marking-deadend", plan="anchored")
    assert score.optimal and score.map_first_error == len(lines) - 1
    # Moves alone still parse under anchored; anchors do not parse as the paper's Plan.
    plain = golden_answer(example_world, "fwd", "marking-deadend", "optimal")
    assert score_optimal(example_world, plain, "fwd", "marking-deadend", plan="anchored").optimal
    assert not score_optimal(example_world, anchored, "fwd", "marking-deadend").parsed
    # With one anchor dropped it still grades by the moves; a garbled line does not parse.
    assert score_optimal(example_world, "\n".join(lines[:-3] + lines[-2:]), "fwd", "marking-deadend",
                         plan="anchored").optimal
    garbled = "\n".join(lines[:-1] + ["(3,2)"])
    assert not score_optimal(example_world, garbled, "fwd", "marking-deadend", plan="anchored").parsed
    with pytest.raises(ValueError, match="unknown plan"):
        score_optimal(example_world, anchored, "fwd", "marking-deadend", plan="cells")


def test_map_first_error_points_at_the_first_wrong_line(example_world):
    wrong = list(GOLDEN_LINES)
    wrong[9] = "cut"  # (1, 0) is new in step 1: labelled "right" in the true map
    score = score_optimal(example_world, "\n".join(wrong), "fwd", "marking-deadend")
    assert score.map_exact is False and score.map_first_error == 9 and score.optimal
    truncated = score_optimal(example_world, "\n".join(GOLDEN_LINES[:10]), "fwd", "marking-deadend")
    assert truncated.map_first_error == 10 and not truncated.parsed


def test_first_difference():
    assert first_difference(["a", "b"], ["a", "b"]) is None
    assert first_difference(["a", "x"], ["a", "b"]) == 1
    assert first_difference(["a"], ["a", "b"]) == 1
    assert first_difference(["a", "b", "c"], ["a", "b"]) == 2


def test_unknown_names_raise(example_world):
    with pytest.raises(ValueError, match="allowed: fwd, bwd"):
        score_optimal(example_world, "", "forward", "none")
    with pytest.raises(ValueError, match="allowed: marking-deadend"):
        score_optimal(example_world, "", "fwd", "deadend")
    with pytest.raises(ValueError, match="reachable-only"):
        score_optimal(example_world, "", "fwd", "dfs")


@given(worlds(), st.sampled_from(DIRECTIONS), st.sampled_from(MODES))
def test_every_conversation_answer_scores_optimal(world, direction, mode):
    for variant in VARIANTS:
        if variant == "dfs":
            continue
        first = conversation(world, direction, variant, mode, prompt="paper")[3]["value"]
        # A reachable answer carries the same Thought: swap its Action tail for the full plan.
        text = (
            first
            if mode == "optimal"
            else first.rsplit("\nAction:", 1)[0] + "\nPlan:\n" + "\n".join(world.optimal_moves())
        )
        if variant == "none" and mode == "reachable":
            text = "Plan:\n" + "\n".join(world.optimal_moves())
        score = score_optimal(world, text, direction, variant)
        assert score.optimal and score.parsed and score.valid and score.reaches_goal
        assert score.map_exact is (True if variant in MAP_VARIANTS else None)
        assert score.map_first_error is None
        assert parse_action(first) == world.optimal_moves()[0] or mode == "optimal"


@given(st.text(max_size=2000))
def test_parser_and_scorer_never_raise_on_text(text):
    parse_answer(text)
    parse_action(text)
    score = score_optimal(_EXAMPLE, text, "bwd", "marking-deadend")
    assert not score.optimal or "Plan:" in text


@given(
    st.lists(
        st.sampled_from(
            ["Thought:", "Plan:", "Action:", "Backtrack:", "up", "right", "(0, 0)", "Step 1:", ""]
        )
    ),
)
def test_section_soup_never_raises(lines):
    text = "\n".join(lines)
    parse_answer(text)
    score_optimal(_EXAMPLE, text, "fwd", "no-all")


@given(
    st.integers(0, len(GOLDEN_FWD_MARKING_DEADEND)),
    st.sets(st.integers(0, len(GOLDEN_LINES) - 1), max_size=5),
)
def test_mutated_golden_answers(cut, deleted):
    truncated = GOLDEN_FWD_MARKING_DEADEND[:cut]
    score = score_optimal(_EXAMPLE, truncated, "fwd", "marking-deadend")
    assert score.optimal == (cut == len(GOLDEN_FWD_MARKING_DEADEND))
    assert (score.map_first_error is None) == score.optimal
    kept = "\n".join(line for i, line in enumerate(GOLDEN_LINES) if i not in deleted)
    score = score_optimal(_EXAMPLE, kept, "fwd", "marking-deadend")
    if deleted:
        # Not always == min(deleted): the golden text repeats lines ("cut"), so a gap can line up again.
        assert score.map_first_error >= min(deleted)


def test_huge_and_odd_inputs():
    # (text, graded optimal): a golden answer with Windows line ends still plans optimally, but its map lines
    # carry a "\r" and so are not the golden map's.
    for text, optimal in [
        ("Plan:\n" + "up\n" * 100_000, False),
        ("Thought:\n\x00\udcff\n☃\nPlan:\nrïght", False),
        ("\r\n".join(GOLDEN_LINES), True),
        (12, False),
    ]:
        score = score_optimal(_EXAMPLE, text, "fwd", "marking-deadend")
        assert score.optimal is optimal and not score.map_exact  # graded, never raised
        assert parse_action(text) in (None, "up", "down", "left", "right")
