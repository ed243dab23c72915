"""Classifying the first wrong line of an answer: section, BFS step, frontier position, line kind, neighbour."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
from hypothesis import given, settings, strategies as st

from pipeline import World
from pipeline.core.map_errors import (
    LINE_KINDS, NEIGHBOURS, STEP_BUCKETS, category, corner_offset, first_wrong_line, label_cells, label_kinds,
    line_kinds, step_bucket,
)
from pipeline.core.texts import golden_answer

# 3 x 3, start (0, 0), goal (2, 2); wall (1, 1), pit (0, 2): the path goes right along y = 0, then up.
WORLD = World(3, 3, 0, 0, ((1, 1),), ((0, 2),), (0, 0), (2, 2))


def _with(variant: str, index: int, line: str | None, direction: str = "bwd") -> str:
    lines = golden_answer(WORLD, direction, variant, "optimal").split("\n")
    if line is None:
        return "\n".join(lines[:index])
    lines[index] = line
    return "\n".join(lines)


def _golden(variant: str, direction: str = "bwd") -> list[str]:
    return golden_answer(WORLD, direction, variant, "optimal").split("\n")


def test_the_golden_answer_has_no_wrong_line():
    for variant in ("marking-deadend", "no-all", "marking-deadend-named", "none", "cot"):
        assert first_wrong_line(WORLD, "fwd", variant, "\n".join(_golden(variant, "fwd"))) is None


def test_labels_name_what_the_neighbour_is_and_how_the_label_is_wrong():
    golden = _golden("marking-deadend")
    # BWD from the goal (2, 2): Step 1 lists (2, 3) outside, (2, 1) free, (1, 2) free, (3, 2) outside.
    assert golden[2:10] == ["(2, 3)", "cut", "(2, 1)", "up", "(1, 2)", "right", "(3, 2)", "cut"]
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", 3, "down"))
    assert (site.section, site.line, site.step, site.state, site.neighbour, site.label_error) == \
        ("thought", "label", 1, 0, "outside", "move for cut")
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", 5, "cut"))
    assert (site.neighbour, site.label_error, site.expected, site.got) == ("free", "cut for move", "up", "cut")
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", 7, "up"))
    assert site.label_error == "wrong move" and category(site) == "label: wrong move"


def test_walls_pits_visited_cells_and_later_frontier_states():
    golden = _golden("marking-deadend")
    step2 = golden.index("Step 2:")
    # Step 2 expands (2, 1) then (1, 2): (2, 1)'s neighbours are (2, 2) visited, (2, 0), (1, 1) wall, (3, 1).
    assert golden[step2 + 1:step2 + 9] == ["(2, 2)", "cut", "(2, 0)", "up", "(1, 1)", "cut", "(3, 1)", "cut"]
    kinds = {}
    for offset in (2, 6):
        site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", step2 + offset, "up"))
        kinds[offset] = (site.step, site.state, site.neighbour)
    assert kinds == {2: (2, 0, "visited"), 6: (2, 0, "wall")}
    # (1, 2)'s neighbours come next: (1, 3) outside, (1, 1) wall, (0, 2) pit, (2, 2) visited.
    assert golden[step2 + 9:step2 + 17] == ["(1, 3)", "cut", "(1, 1)", "cut", "(0, 2)", "cut", "(2, 2)", "cut"]
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", step2 + 14, "right"))
    assert (site.step, site.state, site.neighbour) == (2, 1, "pit")
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", step2 + 13, "(0, 1)"))
    assert (site.line, site.step, site.state, site.neighbour) == ("coordinate", 2, 1, None)


def test_no_marking_labels_visited_cells_with_moves_and_still_tells_them_apart():
    golden = _golden("no-marking")
    step2 = golden.index("Step 2:")
    assert golden[step2 + 1:step2 + 3] == ["(2, 2)", "down"]
    site = first_wrong_line(WORLD, "bwd", "no-marking", _with("no-marking", step2 + 2, "up"))
    assert (site.neighbour, site.label_error) == ("visited", "wrong move")


def test_named_maps_count_states_by_their_from_lines():
    golden = _golden("no-all-named")
    step2 = golden.index("Step 2:")
    assert golden[step2 + 1].startswith("From ")
    second = [i for i, line in enumerate(golden) if line.startswith("From ")][2]
    site = first_wrong_line(WORLD, "bwd", "no-all-named", _with("no-all-named", second, "From (0, 0):"))
    assert (site.line, site.step, site.state) == ("state name", 2, 1)


def test_headers_backtrack_plan_and_length():
    golden = _golden("marking-deadend")
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", 1, "Step 2:"))
    assert (site.line, site.step) == ("step header", 1)
    back = golden.index("Backtrack:")
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", back + 1, "(9, 9)"))
    assert (site.section, site.line, site.step, site.state) == ("backtrack", "backtrack", None, None)
    plan = golden.index("Plan:")
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", _with("marking-deadend", plan + 1, None))
    assert (site.section, site.line, site.got, site.expected) == ("plan", "plan", None, golden[plan + 1])
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", "\n".join(golden + ["up"]))
    assert (site.section, site.line, site.index, site.got) == ("end", "end", len(golden), "up")


def test_step_buckets():
    assert [step_bucket(s) for s in (None, 1, 2, 3, 5, 6, 40)] == [None, *STEP_BUCKETS[:2], STEP_BUCKETS[2],
                                                                  STEP_BUCKETS[2], STEP_BUCKETS[3], STEP_BUCKETS[3]]


@settings(max_examples=200, deadline=None)
@given(st.one_of(st.none(), st.binary(max_size=50), st.text(max_size=300),
                 st.lists(st.sampled_from(["Thought:", "Step 1:", "(2, 2)", "cut", "up", "Plan:", "", "From (1, 1):"]),
                          max_size=60).map("\n".join)))
@pytest.mark.parametrize("variant", ["marking-deadend", "no-all-named", "none"])
def test_model_text_never_raises(variant, text):
    site = first_wrong_line(WORLD, "fwd", variant, text)
    assert site is None or (site.line in LINE_KINDS and site.neighbour in (None, *NEIGHBOURS))


def test_plain_step_headers_count_steps_and_score_like_numbered_ones():
    """With `Step:` headers the steps are still counted, and a numbered header is the wrong line."""
    golden = golden_answer(WORLD, "bwd", "marking-deadend", "optimal", steps="plain").split("\n")
    assert first_wrong_line(WORLD, "bwd", "marking-deadend", "\n".join(golden), steps="plain") is None
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", "\n".join(golden).replace("Step:", "Step 1:", 1),
                            steps="plain")
    assert (site.line, site.step, site.expected, site.got) == ("step header", 1, "Step:", "Step 1:")
    second = [i for i, line in enumerate(golden) if line == "Step:"][1]
    lines = list(golden)
    lines[second + 2] = "cut" if lines[second + 2] != "cut" else "up"
    site = first_wrong_line(WORLD, "bwd", "marking-deadend", "\n".join(lines), steps="plain")
    assert (site.line, site.step, site.state) == ("label", 2, 0)
    numbered = _golden("marking-deadend")
    assert first_wrong_line(WORLD, "bwd", "marking-deadend", "\n".join(golden)).line == "step header"
    assert numbered != golden


@pytest.mark.parametrize("variant", ["marking-deadend", "no-all", "marking-deadend-named"])
def test_label_kinds_are_every_label_line_and_agree_with_the_first_wrong_line(variant):
    golden = _golden(variant)
    kinds = label_kinds(WORLD, "bwd", variant)
    if variant == "marking-deadend":
        assert kinds[:4] == [(3, "outside"), (5, "free"), (7, "free"), (9, "outside")]
        # With MARKING every neighbour but a new free cell is cut.
        assert all((golden[line] == "cut") == (kind != "free") for line, kind in kinds)
    assert all(golden[line] in ("cut", "up", "down", "left", "right") for line, _ in kinds)
    # Without ALL only the new neighbours are listed, all free; with it, walls too.
    seen = {kind for _, kind in kinds}
    assert seen == {"free"} if variant == "no-all" else {"free", "wall", "pit", "outside"} <= seen <= set(NEIGHBOURS)
    for line, kind in kinds:
        wrong = "cut" if golden[line] != "cut" else "up"
        site = first_wrong_line(WORLD, "bwd", variant, "\n".join(golden[:line] + [wrong] + golden[line + 1:]))
        assert (site.index, site.line, site.neighbour) == (line, "label", kind)


def test_line_kinds_name_every_golden_line_and_number_the_moves():
    golden = golden_answer(WORLD, "bwd", "marking-deadend", "optimal").split("\n")
    kinds = line_kinds(WORLD, "bwd", "marking-deadend")
    assert len(kinds) == len(golden)
    labels = label_kinds(WORLD, "bwd", "marking-deadend")
    assert [kind for kind, _ in kinds if kind == "label"] == ["label"] * len(labels)
    backtrack = golden[golden.index("Backtrack:") + 1: golden.index("Plan:")]
    plan = golden[golden.index("Plan:") + 1:]
    tail = kinds[golden.index("Backtrack:") + 1:]
    assert [kind for kind, _ in tail] == ["backtrack cell", "backtrack move"] * (len(backtrack) // 2) + \
        ["backtrack cell", "section header"] + ["plan"] * len(plan)
    assert [move for kind, move in tail if kind == "backtrack move"] == list(range(len(plan)))
    assert [move for kind, move in tail if kind == "plan"] == list(range(len(plan)))
    assert backtrack[1::2] == plan
    anchored = line_kinds(WORLD, "bwd", "marking-deadend", plan="anchored")
    plan_kinds = anchored[golden.index("Plan:") + 1:]
    assert [kind for kind, _ in plan_kinds] == ["plan cell", "plan"] * len(plan) + ["plan cell"]
    assert [move for kind, move in plan_kinds if kind == "plan"] == list(range(len(plan)))
    assert anchored[:golden.index("Plan:") + 1] == kinds[:golden.index("Plan:") + 1]


def test_label_cells_name_each_labels_neighbour_and_its_offset_from_the_low_corner():
    golden = _golden("marking-deadend")
    cells = label_cells(WORLD, "bwd", "marking-deadend")
    assert [(line, kind) for line, kind, _ in cells] == label_kinds(WORLD, "bwd", "marking-deadend")
    assert all(golden[line - 1] == f"({x}, {y})" for line, _, (x, y) in cells)
    shifted = SimpleNamespace(x0=1, y0=3)  # the offset reads the grid's low corner alone
    assert [corner_offset(shifted, cell) for cell in ((1, 3), (5, 3), (2, 4), (0, 3))] == [0, 4, 1, 0]
    assert corner_offset(WORLD, (2, 2)) == 2
