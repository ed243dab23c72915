"""Texts: SPEC golden strings, list formats, the variant switches, conversations and the DFS baseline."""

from __future__ import annotations

import dataclasses
import re

import pytest
from conftest import worlds
from hypothesis import given, strategies as st

from pipeline import World, conversation
from pipeline.core.variants import BASELINES, DIRECTIONS, MAP_VARIANTS, MODES, PAPER_MAP_VARIANTS, PAPER_VARIANTS, VARIANTS
from pipeline.core.texts import (
    INSTRUCTION,
    PLAN_FORMS,
    cell_text,
    plan_lines,
    grid_axes,
    parse_cell,
    PROMPTS,
    golden_answer,
    backtrack_lines,
    cognitive_map,
    cot_thought,
    dfs_moves,
    edge_label_spans,
    free_cells,
    listed_obstacles,
    is_step_header,
    observation,
    prompt_turns,
    task_text,
)
from pipeline.core.world import step


def _world(walls=(), pits=(), size=(3, 3)) -> World:
    return World(size[0], size[1], 0, 0, tuple(walls), tuple(pits), (0, 0), (size[0] - 1, size[1] - 1))


def test_constants():
    assert DIRECTIONS == ("fwd", "bwd")
    assert MODES == ("optimal", "reachable")
    assert BASELINES == ("none", "cot", "dfs")
    assert PAPER_VARIANTS == (
        "marking-deadend",
        "no-marking",
        "no-backtrack",
        "no-marking-no-backtrack",
        "no-all",
        "no-all-no-backtrack",
        "none",
        "cot",
        "dfs",
    )
    assert VARIANTS == (*PAPER_MAP_VARIANTS, *(v + "-named" for v in PAPER_MAP_VARIANTS), *BASELINES)
    assert MAP_VARIANTS["marking-deadend"] == (True, True, True, False)
    assert MAP_VARIANTS["no-all"] == (False, False, True, False)
    assert MAP_VARIANTS["no-all-named"] == (False, False, True, True)
    assert INSTRUCTION.startswith("You are given a rectangular gridworld, where you can move up, down,")
    assert INSTRUCTION.endswith("with either one of 'up', 'down', 'left', or 'right'.")
    assert INSTRUCTION.count("\n\n") == 2


def test_golden_turn_3(example_world, golden):
    assert task_text(example_world) + observation(example_world, example_world.start) == golden["turn_3"]
    assert prompt_turns(example_world, "paper") == [
        {"from": "human", "value": INSTRUCTION},
        {"from": "gpt", "value": "OK"},
        {"from": "human", "value": golden["turn_3"]},
    ]


def test_golden_fwd_marking_deadend(example_world, golden):
    assert golden_answer(example_world, "fwd", "marking-deadend", "optimal") == golden["fwd_marking_deadend"]


def test_golden_bwd_no_all(example_world, golden):
    assert golden_answer(example_world, "bwd", "no-all", "optimal") == golden["bwd_no_all"]


def test_cognitive_map_is_the_answer_without_plan(example_world, golden):
    lines = cognitive_map(example_world, "fwd", all_moves=True, marking=True, backtrack=True)
    assert "\n".join(lines) + "\nPlan:\nright\nright\nup\nright\nup" == golden["fwd_marking_deadend"]


@pytest.mark.parametrize(
    ("world", "expected"),
    [
        (World(2, 2, 0, 0, (), (), (0, 0), (1, 0)), "There is no pit. There is no wall.\n"),
        (_world(walls=[(1, 1)], pits=[(2, 0)]), "The pit is at (2, 0). The wall is at (1, 1).\n"),
        (_world(walls=[(1, 1), (0, 2)]), "There is no pit. The wall is at (1, 1), and (0, 2).\n"),
        (
            _world(walls=[(0, 1), (2, 1), (1, 1)], size=(4, 2)),
            "There is no pit. The wall is at (0, 1), (2, 1), and (1, 1).\n",
        ),
    ],
)
def test_obstacle_listings(world, expected):
    assert task_text(world).endswith(expected)


def test_observation_order_and_blocked_moves(example_world):
    assert observation(example_world, (2, 1)) == "Current:\n(2, 1)\nPossible:\n(2, 0)\ndown\n(3, 1)\nright"
    assert observation(example_world, (0, 1)) == "Current:\n(0, 1)\nPossible:\n(0, 2)\nup\n(0, 0)\ndown"


def test_variants_differ_only_by_switches(example_world):
    fwd_no_marking = golden_answer(example_world, "fwd", "no-marking", "optimal")
    assert "cut" not in fwd_no_marking
    # Marking only relabels: same number of lines, same cells.
    marked = golden_answer(example_world, "fwd", "marking-deadend", "optimal").split("\n")
    assert len(marked) == len(fwd_no_marking.split("\n"))
    assert golden_answer(example_world, "fwd", "no-backtrack", "optimal") == golden_answer(
        example_world, "fwd", "marking-deadend", "optimal"
    ).replace("\n".join([""] + backtrack_lines(example_world, "fwd")), "")
    no_all = golden_answer(example_world, "fwd", "no-all", "optimal")
    assert "cut" not in no_all and "(-1, 0)" not in no_all


def test_bwd_labels_are_moves_towards_the_state(example_world):
    lines = cognitive_map(example_world, "bwd", all_moves=True, marking=False, backtrack=False)
    # Step 1 from the goal (3, 2): neighbours (3, 3), (3, 1), (2, 2), (4, 2) labelled down, up, right, left.
    assert lines[:10] == [
        "Thought:",
        "Step 1:",
        "(3, 3)",
        "down",
        "(3, 1)",
        "up",
        "(2, 2)",
        "right",
        "(4, 2)",
        "left",
    ]


def test_cot_and_none(example_world):
    assert cot_thought(example_world, "bwd")[:7] == [
        "Thought:",
        "Step 1:",
        "Step 2:",
        "Step 3:",
        "Step 4:",
        "Step 5:",
        "Backtrack:",
    ]
    assert golden_answer(example_world, "fwd", "none", "optimal") == "Plan:\nright\nright\nup\nright\nup"
    assert golden_answer(example_world, "bwd", "none", "reachable") == "Action:\nright"
    assert conversation(example_world, "fwd", "none", "reachable") == conversation(
        example_world, "bwd", "none", "reachable"
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (("up", "marking-deadend", "optimal"), "unknown direction 'up'; allowed: fwd, bwd"),
        (("fwd", "marking", "optimal"), "unknown variant 'marking'; allowed: marking-deadend, no-marking"),
        (("fwd", "none", "multi"), "unknown mode 'multi'; allowed: optimal, reachable"),
        (("fwd", "dfs", "optimal"), "'dfs' is reachable-only"),
    ],
)
def test_unknown_names(example_world, args, message):
    with pytest.raises(ValueError, match=message):
        golden_answer(example_world, *args)
    with pytest.raises(ValueError, match=message):
        conversation(example_world, *args)


def test_reachable_conversation_shape(example_world):
    turns = conversation(example_world, "bwd", "marking-deadend", "reachable", prompt="paper")
    assert [t["from"] for t in turns] == ["human", "gpt"] * (len(turns) // 2)
    assert turns[3]["value"].endswith("\nAction:\nright")
    assert [t["value"] for t in turns[5::2]] == ["right", "up", "right", "up"]
    assert turns[4]["value"] == observation(example_world, (1, 0))
    assert len(conversation(example_world, "bwd", "marking-deadend", "optimal", prompt="paper")) == 4


def test_dfs_is_seeded_and_walks_to_the_goal(example_world):
    walks = {tuple(dfs_moves(example_world, seed)) for seed in range(30)}
    assert len(walks) > 1  # the start has two ways out: the seed matters
    assert dfs_moves(example_world, 4) == dfs_moves(example_world, 4)
    assert conversation(example_world, "fwd", "dfs", "reachable", seed=4) == conversation(
        example_world, "fwd", "dfs", "reachable", seed=4
    )


@given(worlds())
def test_dfs_walk_is_a_legal_walk_ending_at_the_goal(world):
    cell = world.start
    moves = dfs_moves(world, seed=1)
    for move in moves:
        cell = step(cell, move)
        assert world.is_free(cell)
    assert cell == world.goal
    # Each tree edge is crossed at most twice (there and back).
    assert len(moves) <= 2 * (world.size_x * world.size_y)


@given(worlds())
def test_map_lists_every_cell_once_as_new(world):
    """Without all-moves each reachable cell appears at most once as new, and the target exactly once."""
    for direction in DIRECTIONS:
        lines = cognitive_map(world, direction, all_moves=False, marking=False, backtrack=False)
        cells = [line for line in lines[1:] if line.startswith("(")]
        assert len(cells) == len(set(cells))
        target = world.goal if direction == "fwd" else world.start
        last_step = lines[max(i for i, line in enumerate(lines) if line.startswith("Step ")) :]
        assert f"({target[0]}, {target[1]})" in last_step
        assert f"({target[0]}, {target[1]})" not in lines[: -len(last_step)]


@pytest.mark.parametrize("offset", [(-3, -5), (40, 70)])
def test_maps_anywhere_in_the_plane(example_world, offset):
    """Coordinates outside the 20 x 20 frame still render: the text is the example's, shifted."""
    dx, dy = offset
    shift = lambda c: (c[0] + dx, c[1] + dy)  # noqa: E731
    moved = World(
        4,
        3,
        dx,
        dy,
        tuple(map(shift, example_world.walls)),
        tuple(map(shift, example_world.pits)),
        shift(example_world.start),
        shift(example_world.goal),
    )
    lines = golden_answer(moved, "fwd", "marking-deadend", "optimal").split("\n")
    golden = golden_answer(example_world, "fwd", "marking-deadend", "optimal").split("\n")
    assert len(lines) == len(golden)
    assert lines[2] == f"({dx}, {dy + 1})" and lines[4] == f"({dx}, {dy - 1})"


def test_task_prompt_is_the_paper_prompt_without_the_instruction(example_world, golden):
    assert PROMPTS == ("paper", "task", "cells", "axes")
    paper, task = prompt_turns(example_world, "paper"), prompt_turns(example_world, "task")
    assert task == paper[2:] == [{"from": "human", "value": golden["turn_3"]}]
    for mode in MODES:
        assert conversation(example_world, "bwd", "marking-deadend", mode, prompt="task") == \
            conversation(example_world, "bwd", "marking-deadend", mode, prompt="paper")[2:]
    with pytest.raises(ValueError, match="unknown prompt 'none'; allowed: paper, task, cells, axes"):
        prompt_turns(example_world, "none")


def test_cells_prompt_golden(example_world, golden):
    """`prompt="cells"` (not in the paper): the task turn with the free cells listed after the walls, in an
    order drawn from the world alone; the answers do not change."""
    [turn] = prompt_turns(example_world, "cells")
    assert turn == {"from": "human", "value": (
        "Grid is from (0, 0) to (3, 2). Goal: (3, 2)\nCurrent: (0, 0)\nThe pit is at (3, 0). The wall is at "
        "(1, 1), and (2, 2). The free cell is at (3, 1), (1, 2), (0, 2), (0, 0), (3, 2), (0, 1), (2, 0), (1, 0), "
        "and (2, 1).\nCurrent:\n(0, 0)\nPossible:\n(0, 1)\nup\n(1, 0)\nright")}
    assert turn["value"].replace(" The free cell is at (3, 1), (1, 2), (0, 2), (0, 0), (3, 2), (0, 1), (2, 0), "
                                 "(1, 0), and (2, 1).", "") == golden["turn_3"]
    for mode in MODES:
        assert conversation(example_world, "bwd", "marking-deadend", mode, prompt="cells")[1:] == \
            conversation(example_world, "bwd", "marking-deadend", mode, prompt="task")[1:]


def test_axes_prompt_golden(example_world, golden):
    """`prompt="axes"` (not in the paper): the task turn with the grid's columns and rows listed after its
    bounds, each in an order drawn from the world alone; the answers do not change."""
    [turn] = prompt_turns(example_world, "axes")
    axes = " Columns: 3, 2, 0, 1. Rows: 0, 1, 2."
    assert turn == {"from": "human", "value": (
        f"Grid is from (0, 0) to (3, 2).{axes} Goal: (3, 2)\nCurrent: (0, 0)\nThe pit is at (3, 0). The wall is "
        "at (1, 1), and (2, 2).\nCurrent:\n(0, 0)\nPossible:\n(0, 1)\nup\n(1, 0)\nright")}
    assert turn["value"].replace(axes, "") == golden["turn_3"]
    for mode in MODES:
        assert conversation(example_world, "bwd", "marking-deadend", mode, prompt="axes")[1:] == \
            conversation(example_world, "bwd", "marking-deadend", mode, prompt="task")[1:]


def test_grid_axes_are_every_column_and_row_once_in_an_order_of_the_world_alone(example_world):
    def moved(dx: int, dy: int) -> World:
        shift = lambda c: (c[0] + dx, c[1] + dy)  # noqa: E731
        w = example_world
        return World(4, 3, dx, dy, tuple(map(shift, w.walls)), tuple(map(shift, w.pits)), shift(w.start), shift(w.goal))

    columns, rows = grid_axes(moved(2, 1))
    assert sorted(columns) == [2, 3, 4, 5] and sorted(rows) == [1, 2, 3]
    swapped = dataclasses.replace(moved(2, 1), start=(5, 3), goal=(2, 1))
    assert grid_axes(swapped) == (columns, rows)   # drawn from the bounds alone
    relative = {tuple(c - dx for c in grid_axes(moved(dx, 0))[0]) for dx in range(3)}
    assert len(relative) > 1   # not one order, shifted


def test_distractors_golden(example_world, golden):
    """`listed_obstacles` with distractors (not in the paper; train prompts only): cells of the frame outside the
    grid join the pit and wall lists at places drawn from the world alone; the answers do not change."""
    obstacles = listed_obstacles(example_world, 6, 6)
    assert obstacles == (((4, 3), (3, 0)), ((1, 4), (1, 5), (1, 1), (2, 5), (0, 3), (2, 2)))
    [turn] = prompt_turns(example_world, "task", obstacles)
    assert turn["value"] == golden["turn_3"].replace(
        "The pit is at (3, 0). The wall is at (1, 1), and (2, 2).",
        "The pit is at (4, 3), and (3, 0). The wall is at (1, 4), (1, 5), (1, 1), (2, 5), (0, 3), and (2, 2).")
    assert listed_obstacles(example_world, 0, 6) == (example_world.pits, example_world.walls)
    for mode in MODES:
        assert conversation(example_world, "bwd", "marking-deadend", mode, obstacles=obstacles)[1:] == \
            conversation(example_world, "bwd", "marking-deadend", mode)[1:]


@given(worlds(), st.integers(0, 12))
def test_distractors_are_frame_cells_outside_the_grid_added_to_the_worlds_own_lists(world, most):
    pits, walls = listed_obstacles(world, most, 8)
    assert listed_obstacles(world, most, 8) == (pits, walls)   # drawn from the world alone
    extra = [c for c in (*pits, *walls) if c not in world.pits and c not in world.walls]
    assert len(extra) == len(pits) + len(walls) - len(world.pits) - len(world.walls) <= most
    assert len(set(extra)) == len(extra)
    for x, y in extra:
        assert 0 <= x < 8 and 0 <= y < 8 and not (world.x0 <= x <= world.x1 and world.y0 <= y <= world.y1)
    # the world's own obstacles keep their lists and their order
    assert [c for c in pits if c in world.pits] == list(world.pits)
    assert [c for c in walls if c in world.walls] == list(world.walls)


@given(worlds())
def test_free_cells_are_every_open_cell_of_the_grid_once(world):
    cells = free_cells(world)
    grid = {(x, y) for x in range(world.x0, world.x1 + 1) for y in range(world.y0, world.y1 + 1)}
    assert sorted(cells) == sorted(grid - set(world.walls) - set(world.pits))
    assert world.start in cells and world.goal in cells
    assert free_cells(world) == cells       # drawn from the world alone: the same every time


@pytest.mark.parametrize("direction", DIRECTIONS)
@pytest.mark.parametrize("variant", list(PAPER_MAP_VARIANTS))
def test_named_map_is_the_paper_map_with_a_from_line_per_expanded_state(variant, direction):
    world = _world(walls=[(1, 1)], pits=[(0, 2)], size=(3, 3))
    plain = golden_answer(world, direction, variant, "optimal").split("\n")
    named = golden_answer(world, direction, variant + "-named", "optimal").split("\n")
    assert [line for line in named if not line.startswith("From ")] == plain
    # One From line per expanded state, naming it, right after its step header or the previous state's lines.
    froms = [line for line in named if line.startswith("From ")]
    root = world.start if direction == "fwd" else world.goal
    assert froms[0] == f"From ({root[0]}, {root[1]}):"
    assert named[named.index("Step 1:") + 1] == froms[0]
    expanded = [line.split("From ")[1][:-1] for line in froms]
    assert len(expanded) == len(set(expanded))


def test_named_golden_bwd_marking_deadend():
    # A 2 x 2 world, wall at (1, 0): BFS from the goal (1, 1) reaches (0, 1) then the start (0, 0).
    world = _world(walls=[(1, 0)], size=(2, 2))
    assert golden_answer(world, "bwd", "marking-deadend-named", "optimal") == "\n".join([
        "Thought:", "Step 1:", "From (1, 1):", "(1, 2)", "cut", "(1, 0)", "cut", "(0, 1)", "right", "(2, 1)", "cut",
        "Step 2:", "From (0, 1):", "(0, 2)", "cut", "(0, 0)", "up", "(-1, 1)", "cut", "(1, 1)", "cut",
        "Backtrack:", "(0, 0)", "up", "(0, 1)", "right", "(1, 1)", "Plan:", "up", "right"])


def test_plain_step_headers_golden(example_world):
    """`steps="plain"` (not in the paper) writes `Step:` where the paper writes `Step k:`; nothing else moves."""
    assert golden_answer(example_world, "bwd", "no-all", "optimal", steps="plain") == (
        "Thought:\nStep:\n(3, 1)\nup\nStep:\n(2, 1)\nright\nStep:\n(2, 0)\nup\nStep:\n(1, 0)\nright\nStep:\n(0, 0)\n"
        "right\nBacktrack:\n(0, 0)\nright\n(1, 0)\nright\n(2, 0)\nup\n(2, 1)\nright\n(3, 1)\nup\n(3, 2)\n"
        "Plan:\nright\nright\nup\nright\nup")
    assert cot_thought(example_world, "fwd", "plain")[:7] == ["Thought:", *["Step:"] * 5, "Backtrack:"]
    for variant in (*MAP_VARIANTS, "cot"):
        numbered = golden_answer(example_world, "fwd", variant, "optimal").split("\n")
        plain = golden_answer(example_world, "fwd", variant, "optimal", steps="plain").split("\n")
        assert [re.sub(r"^Step \d+:$", "Step:", line) for line in numbered] == plain
    assert golden_answer(example_world, "fwd", "none", "optimal", steps="plain") == golden_answer(
        example_world, "fwd", "none", "optimal")
    assert all(is_step_header(h) for h in ("Step:", "Step 1:", "Step 12:")) and not is_step_header("(1, 2)")
    with pytest.raises(ValueError, match="unknown steps 'roman'; allowed: numbered, plain"):
        conversation(example_world, "fwd", "marking-deadend", "optimal", steps="roman")


def test_anchored_plan_golden(example_world):
    """`plan="anchored"` (not in the paper) writes the cell before each move and the goal last; for bwd the Plan is
    then the Backtrack's own lines, for fwd the same walk from the start; nothing before the Plan moves."""
    anchored = golden_answer(example_world, "bwd", "no-all", "optimal", plan="anchored")
    assert anchored.split("Plan:\n")[1] == (
        "(0, 0)\nright\n(1, 0)\nright\n(2, 0)\nup\n(2, 1)\nright\n(3, 1)\nup\n(3, 2)")
    assert anchored.split("Plan:\n")[1] == anchored.split("Backtrack:\n")[1].split("\nPlan:")[0]
    for variant in (*MAP_VARIANTS, "cot"):
        for direction in DIRECTIONS:
            moves = golden_answer(example_world, direction, variant, "optimal").split("\n")
            lines = golden_answer(example_world, direction, variant, "optimal", plan="anchored").split("\n")
            plan = moves.index("Plan:")
            assert lines[:plan + 1] == moves[:plan + 1]
            assert lines[plan + 2::2] == moves[plan + 1:] and lines[plan + 1] == "(0, 0)" and lines[-1] == "(3, 2)"
    # NONE and DFS write no Thought: their Plan stays the paper's; the reachable setting has no Plan.
    for variant, mode in (("none", "optimal"), ("none", "reachable"), ("marking-deadend", "reachable")):
        assert conversation(example_world, "fwd", variant, mode, plan="anchored") == conversation(
            example_world, "fwd", variant, mode)
    assert plan_lines(example_world, ["up"], "anchored") == ["(0, 0)", "up", "(0, 1)"]
    assert PLAN_FORMS == ("moves", "anchored")
    with pytest.raises(ValueError, match="unknown plan 'cells'; allowed: moves, anchored"):
        golden_answer(example_world, "fwd", "marking-deadend", "optimal", plan="cells")


def test_parse_cell_reads_back_what_cell_text_writes_and_nothing_else():
    for cell in ((0, 0), (-1, 5), (12, -3)):
        assert parse_cell(cell_text(cell)) == cell
    assert [parse_cell(text) for text in ("(1,2)", " (1, 2)", "(1, 2) ", "cut", "Step 1:")] == [None] * 5


def test_edge_labels_are_the_cut_of_neighbours_beyond_a_grid_as_long_as_the_largest_train_grid():
    # Grid (1, 2)-(2, 5): 2 wide, 4 high. With train sides up to 4, the cells just above and below it are the
    # edge labels' neighbours (a 4-high grid), those left and right of it are not (it is 2 wide, not 4).
    world = World(2, 4, 1, 2, ((2, 4), (2, 2)), (), (1, 2), (2, 5))
    answer = golden_answer(world, "bwd", "marking-deadend", "optimal")
    assert answer.startswith("Thought:\nStep 1:\n(2, 6)\ncut\n(2, 4)\ncut\n(1, 5)\nright\n(3, 5)\ncut\nStep 2:\n"
                             "(1, 6)\ncut\n(1, 4)\nup\n(0, 5)\ncut\n")
    spans = edge_label_spans(world, answer, (4, 4))
    assert spans == [(24, 27), (78, 81)]
    assert [answer[a - 7:b] for a, b in spans] == ["(2, 6)\ncut", "(1, 6)\ncut"]
    # As wide as the widest train grid (2): the left and right neighbours' labels too; neither axis: none.
    wide = [answer[a - 7:b] for a, b in edge_label_spans(world, answer, (2, 6))]
    assert wide[:4] == ["(3, 5)\ncut", "(0, 5)\ncut", "(0, 4)\ncut", "(0, 3)\ncut"]
    assert all(parse_cell(text[:6]) is not None and not world.in_grid(parse_cell(text[:6])) for text in wide)
    assert edge_label_spans(world, answer, (3, 3)) == []
    # Cells inside the grid (the backtrack, every expanded neighbour) are never edge cells.
    assert edge_label_spans(world, "Backtrack:\n(1, 2)\nup\n(1, 3)", (4, 4)) == []
