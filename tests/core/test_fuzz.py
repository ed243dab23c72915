"""Untrusted model output: 10,000 fuzzed answers through parsing, scoring, eval records and the env.

A model can answer anything: a golden answer with a line dropped, doubled or mangled, headers twice or
missing, moves in another case, NUL bytes and emoji, a giant blank, no text at all, or plain garbage. None of
it may raise: parsing returns None/False, scoring grades it, the env ends the episode as INVALID or DEADEND.
The corpus is deterministic (a seeded `random.Random`), so a failure reproduces with the case it prints.
"""

from __future__ import annotations

import random

import pytest

from pipeline.core.environment import GridEnv, Outcome
from pipeline.core.episodes import optimal_episode, reachable_episode
from pipeline.core.generators import GeneratorConfig, sample_world
from pipeline.core.scoring import parse_action, parse_answer, plan_moves, score_optimal
from pipeline.core.texts import golden_answer
from pipeline.core.variants import MAP_VARIANTS
from pipeline.core.world import MOVES, World

N_OUTPUTS = 10_000
SEED = 20240607
_WORDS = [*MOVES, "Up", "UP", " up", "right ", "upp", "ri ght", "north", "Thought:", "Plan:", "Action:",
          "Backtrack:", "Step 1:", "cut", "(0, 0)", "(-1, 99)", "(3,2)", "(", ")", ",", "", " ", "\t",
          "\r", "\x00", "\u200b", "\ufffd", "🙂", "</s>", "<gpt>", "<human>", "nan", "-1", "9" * 40]
_OPTIMAL_VARIANTS = (*MAP_VARIANTS, "none", "cot")
_STATS = {"size_x": 0, "size_y": 0, "optimal_length": 0, "dead_ends": 0, "up_right_only": False,
          "interpolated": True}


def _worlds(example: World) -> list[World]:
    rng = random.Random(SEED)
    cfg = GeneratorConfig(size_x=(2, 8), size_y=(2, 8), frame=10)
    return [example, *(sample_world(rng, cfg) for _ in range(5))]


def _mutate(rng: random.Random, text: str) -> object:
    """One random corruption of a golden answer (or, sometimes, something that is not text at all)."""
    lines = text.split("\n")
    kind = rng.randrange(14)
    if kind == 0 and lines:  # drop a line
        del lines[rng.randrange(len(lines))]
    elif kind == 1 and lines:  # duplicate a line (a header twice, a move twice)
        i = rng.randrange(len(lines))
        lines.insert(i, lines[i])
    elif kind == 2 and len(lines) > 1:  # swap two lines
        i, j = rng.randrange(len(lines)), rng.randrange(len(lines))
        lines[i], lines[j] = lines[j], lines[i]
    elif kind == 3 and lines:  # replace a line by a random word
        lines[rng.randrange(len(lines))] = rng.choice(_WORDS)
    elif kind == 4:  # insert random words anywhere
        for _ in range(rng.randint(1, 5)):
            lines.insert(rng.randint(0, len(lines)), rng.choice(_WORDS))
    elif kind == 5:  # cut off mid-character stream (max_new_tokens reached)
        return text[: rng.randint(0, len(text))]
    elif kind == 6:  # other line endings and padding
        return rng.choice(["\r\n", "\n\n", " \n ", "\n\t"]).join(lines)
    elif kind == 7:  # random bytes, decoded or not
        raw = bytes(rng.randrange(256) for _ in range(rng.randint(0, 200)))
        return raw if rng.random() < 0.5 else raw.decode("latin-1")
    elif kind == 8:  # random printable garbage with newlines
        return "".join(rng.choices("updownleftrightPlanAction:Thought\n ()0123456789,-", k=rng.randint(0, 300)))
    elif kind == 9:  # not a string at all
        return rng.choice([None, 0, 1.5, [], {}, ["up"], b"Plan:\nup", True])
    elif kind == 10:  # case and whitespace games on every move
        return "\n".join(line.upper() if line in MOVES and rng.random() < 0.5 else f" {line} " for line in lines)
    elif kind == 11:  # a very long answer (a model that never stops)
        return text + "\n" + "\n".join(rng.choices(_WORDS, k=300)) * rng.randint(1, 4)
    elif kind == 12:  # the sections repeated or reordered
        return "\n".join(lines + lines) if rng.random() < 0.5 else "\n".join(reversed(lines))
    else:  # empty-ish
        return rng.choice(["", "\n", " ", "Plan:", "Action:", "Thought:\nPlan:", "Action:\n", "Plan:\n\n"])
    return "\n".join(lines)


def _corpus(worlds: list[World]) -> list[tuple[World, str, str, str, object]]:
    """(world, direction, variant, mode, output) cases: mostly mutated golden answers, some pure garbage."""
    rng = random.Random(SEED)
    goldens: dict[tuple, str] = {}
    cases = []
    for _ in range(N_OUTPUTS):
        index = rng.randrange(len(worlds))
        world = worlds[index]
        direction = rng.choice(("fwd", "bwd"))
        mode = rng.choice(("optimal", "reachable"))
        variant = rng.choice(_OPTIMAL_VARIANTS + (("dfs",) if mode == "reachable" else ()))
        key = (index, direction, variant, mode, rng.randrange(3))  # the last: the DFS walk's seed
        if key not in goldens:
            goldens[key] = golden_answer(world, direction, variant, mode, seed=key[-1])
        golden = goldens[key]
        output = golden if rng.random() < 0.05 else _mutate(rng, golden)
        if rng.random() < 0.3:  # mutations of mutations
            output = _mutate(rng, output if isinstance(output, str) else golden)
        cases.append((world, direction, variant, mode, output))
    return cases


def _play(world: World, output: object) -> Outcome:
    """Feed the answer to the env as a reachable first turn, then as a bare later answer."""
    env = GridEnv(world, max_moves=3)
    env.reset()
    result = env.step(parse_action(output))
    while not result.done:
        result = env.step(parse_action(output))
    assert result.outcome in Outcome
    env.reset()
    raw = env.step(output if isinstance(output, str) else None)  # the raw text, unparsed
    assert raw.done or raw.observation
    return result.outcome


def test_ten_thousand_fuzzed_outputs_never_raise(example_world):
    worlds = _worlds(example_world)
    cases = _corpus(worlds)
    assert len(cases) == N_OUTPUTS
    outcomes, optimal_hits, parsed_plans = {}, 0, 0
    for number, (world, direction, variant, mode, output) in enumerate(cases):
        try:
            parsed = parse_answer(output)
            moves = plan_moves(parsed)
            assert moves is None or all(m in MOVES for m in moves)
            action = parse_action(output)
            assert action is None or action in MOVES
            if mode == "optimal":
                score = score_optimal(world, output, direction, variant)
                record = optimal_episode(number, world, _STATS, output, None, direction, variant).to_dict()
                assert record["success"] == score.optimal and record["outcome"] in ("success", "fail")
                optimal_hits += score.optimal
                parsed_plans += score.parsed
                assert score.valid or not score.reaches_goal
                assert not score.optimal or (score.valid and score.reaches_goal)
            else:
                outcome = _play(world, output)
                outcomes[outcome] = outcomes.get(outcome, 0) + 1
                record = reachable_episode(number, _STATS, outcome.value, [], None).to_dict()
                assert record["success"] == (outcome is Outcome.SUCCESS)
        except Exception as error:  # pragma: no cover - the message is the point
            pytest.fail(f"case {number} ({direction} {variant} {mode}) raised {error!r} on {output!r:.300}")
    # The corpus really exercises both sides: intact golden answers succeed, mangled ones do not.
    assert 0 < optimal_hits < parsed_plans
    assert {Outcome.INVALID, Outcome.DEADEND} <= set(outcomes)


def test_the_corpus_is_deterministic(example_world):
    first, again = _corpus(_worlds(example_world)), _corpus(_worlds(example_world))
    assert [repr(case) for case in first] == [repr(case) for case in again]


@pytest.mark.parametrize("output", [None, b"\xff\xfe", 12, "", "\x00" * 10, "Plan:\n" + "up\n" * 10_000,
                                    "Action:\nUP", "Action:\n\nup", "Plan:\nup\nPlan:\ndown", "Thought:\nThought:"])
def test_edge_outputs_are_graded_not_raised(example_world, output):
    score = score_optimal(example_world, output, "fwd", "marking-deadend")
    assert score.optimal is False and score.map_exact is False
    assert parse_action(output) in (None, *MOVES)
    move = parse_action(output)
    result = GridEnv(example_world).step(move)
    # Not a move: the episode ends INVALID; a move from the start: up is free, the others leave the grid or hit a wall.
    expected = {None: Outcome.INVALID, "up": None, "right": None}.get(move, Outcome.DEADEND)
    assert result.outcome is expected and result.done == (expected is not None)
