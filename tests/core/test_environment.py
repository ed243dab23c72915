"""GridEnv: outcomes, the move limit, and replaying every reachable conversation."""

from __future__ import annotations

import pytest
from conftest import worlds
from hypothesis import given
from hypothesis import strategies as st

from pipeline import conversation
from pipeline.core.environment import EpisodeTranscript, GridEnv, Outcome
from pipeline.core.scoring import parse_action, parse_action_paper
from pipeline.core.texts import prompt_turns
from pipeline.core.variants import DIRECTIONS, VARIANTS


def test_reset_is_the_third_prompt_turn(example_world, golden):
    env = GridEnv(example_world)
    assert env.reset() == golden["turn_3"] == prompt_turns(example_world, "paper")[2]["value"]
    assert env.position == example_world.start and env.moves == [] and not env.done


def test_success(example_world):
    env = GridEnv(example_world)
    env.reset()
    results = [env.step(m) for m in example_world.optimal_moves()]
    assert [r.done for r in results] == [False] * 4 + [True]
    assert results[-1].outcome is Outcome.SUCCESS and results[-1].observation is None
    assert results[0].observation == "Current:\n(1, 0)\nPossible:\n(0, 0)\nleft\n(2, 0)\nright"
    transcript = env.transcript()
    assert transcript.outcome is Outcome.SUCCESS and transcript.n_moves == transcript.optimal_length == 5
    assert transcript.to_dict()["outcome"] == "success"


@pytest.mark.parametrize(
    "moves",
    [["left"], ["down"], ["up", "right"], ["right", "right", "right"]],  # outside, outside, wall, pit
)
def test_deadend(example_world, moves):
    env = GridEnv(example_world)
    env.reset()
    result = None
    for move in moves:
        result = env.step(move)
    assert result.done and result.outcome is Outcome.DEADEND
    assert env.moves == moves


@pytest.mark.parametrize("answer", [None, "", "Up", "jump", "up\n", 3])
def test_invalid(example_world, answer):
    env = GridEnv(example_world)
    env.reset()
    result = env.step(answer)
    assert result.outcome is Outcome.INVALID and env.moves == []
    assert env.transcript().to_dict()["invalid_answer"] == answer


def test_max_moves(example_world):
    env = GridEnv(example_world, max_moves=200)
    env.reset()
    results = [env.step(m) for m in ["up", "down"] * 100]
    assert not any(r.done for r in results[:-1])
    assert results[-1].outcome is Outcome.MAX_STEP
    assert env.transcript().n_moves == 200


def test_goal_on_the_last_allowed_move_is_success(example_world):
    env = GridEnv(example_world, max_moves=5)
    env.reset()
    outcomes = [env.step(m).outcome for m in example_world.optimal_moves()]
    assert outcomes[-1] is Outcome.SUCCESS


def test_step_after_done_and_reset(example_world):
    env = GridEnv(example_world)
    env.reset()
    env.step("left")
    with pytest.raises(RuntimeError, match="reset"):
        env.step("up")
    env.reset()
    assert env.step("up").outcome is None and env.position == (0, 1)


def test_bad_max_moves(example_world):
    with pytest.raises(ValueError, match="max_moves"):
        GridEnv(example_world, max_moves=0)


def test_record_is_a_dataclass_row(example_world):
    env = GridEnv(example_world)
    env.reset()
    env.step("up")
    row = env.transcript().to_dict()
    assert row == {
        "outcome": None,
        "moves": ["up"],
        "n_moves": 1,
        "optimal_length": 5,
        "size_x": 4,
        "size_y": 3,
        "final_position": [0, 1],
        "invalid_answer": None,
    }
    assert isinstance(env.transcript(), EpisodeTranscript)


def _moves_of(turns: list[dict]) -> list[str]:
    first = turns[3]["value"].split("\n")
    assert first[-2] == "Action:"
    return [first[-1]] + [t["value"] for t in turns[5::2]]


@given(worlds(), st.sampled_from([v for v in VARIANTS]), st.sampled_from(DIRECTIONS), st.integers(0, 99))
def test_replaying_a_reachable_conversation_succeeds(world, variant, direction, seed):
    turns = conversation(world, direction, variant, "reachable", seed=seed, prompt="paper")
    env = GridEnv(world)
    assert env.reset() == turns[2]["value"]
    moves = _moves_of(turns)
    observations = [env.step(m) for m in moves]
    assert observations[-1].outcome is Outcome.SUCCESS
    assert [r.observation for r in observations[:-1]] == [t["value"] for t in turns[4::2]]
    if variant != "dfs":
        assert env.transcript().n_moves == env.transcript().optimal_length


def _walk_to_the_goal(env, world, rules_answer=lambda move: move):
    for move in world.optimal_moves():
        result = env.step(move, rules_answer(move))
    return result


def test_the_papers_rules_fail_a_goal_reached_on_the_last_allowed_answer(example_world):
    n = len(example_world.optimal_moves())
    assert _walk_to_the_goal(GridEnv(example_world, max_moves=n), example_world).outcome is Outcome.SUCCESS
    paper = GridEnv(example_world, max_moves=n, rules="paper")
    assert _walk_to_the_goal(paper, example_world).outcome is Outcome.MAX_STEP
    assert len(paper.moves) == n
    assert _walk_to_the_goal(GridEnv(example_world, max_moves=n + 1, rules="paper"), example_world).outcome \
        is Outcome.SUCCESS


def test_the_papers_rules_end_an_empty_answer_max_step_and_ours_invalid(example_world):
    assert GridEnv(example_world).step(None, "").outcome is Outcome.INVALID
    assert GridEnv(example_world, rules="paper").step(None, "").outcome is Outcome.MAX_STEP
    assert GridEnv(example_world, rules="paper").step(None, "left up").outcome is Outcome.INVALID
    with pytest.raises(ValueError, match="rules='strict'"):
        GridEnv(example_world, rules="strict")


@pytest.mark.parametrize("answer, ours, papers", [
    ("Thought:\nStep 1:\nAction:\nup", "up", "up"),
    ("Action:\nup\n", "up", None),           # the paper takes everything after Action:\n, newline included
    ("Action:\n up", "up", None),
    ("up", "up", "up"),
    ("Plan:\nright\nAction:\nup", "up", None),  # Plan:\n comes first for the paper: "right\nAction:\nup"
    ("Action:\n<think>left", None, "left"),
    ("", None, None),
])
def test_the_papers_move_is_everything_after_action(answer, ours, papers):
    assert parse_action(answer) == ours and parse_action_paper(answer) == papers
