"""World record: validation, shortest path, JSON round trip and the paper's test file."""

from __future__ import annotations

import copy
import json
from collections import deque

import pytest
from conftest import free_cells_form_a_tree, worlds
from hypothesis import given

from pipeline.core.generators import world_stats
from pipeline.core.world import MOVES, World, WorldError, load_worlds, move_between, save_worlds, step


def _json(**changes) -> dict:
    q = {
        "world_size_x": 4,
        "world_size_y": 3,
        "wall": [[1, 1], [2, 2]],
        "pit": [[3, 0]],
        "start": [0, 0],
        "goal": [3, 2],
        "gridstart_x": 0,
        "gridstart_y": 0,
    }
    q.update(changes)
    return {"question": q}


def _count_shortest_paths(world: World) -> int:
    """Independent check: number of shortest start-goal paths by BFS layer counting."""
    dist, ways = {world.start: 0}, {world.start: 1}
    queue = deque([world.start])
    while queue:
        x, y = queue.popleft()
        for dx, dy in MOVES.values():
            n = (x + dx, y + dy)
            if not world.is_free(n):
                continue
            if n not in dist:
                dist[n], ways[n] = dist[(x, y)] + 1, 0
                queue.append(n)
            if dist[n] == dist[(x, y)] + 1:
                ways[n] += ways[(x, y)]
    return ways.get(world.goal, 0)


def test_example_world(example_world):
    assert (example_world.x1, example_world.y1) == (3, 2)
    assert example_world.shortest_path() == [(0, 0), (1, 0), (2, 0), (2, 1), (3, 1), (3, 2)]
    assert example_world.optimal_moves() == ["right", "right", "up", "right", "up"]
    assert example_world.is_free((0, 2)) and not example_world.is_free((1, 1))
    assert not example_world.is_free((3, 0)) and not example_world.is_free((4, 1))
    assert example_world.in_grid((3, 0)) and not example_world.in_grid((-1, 0))
    assert World.from_json(_json()) == example_world


def test_moves_table_order():
    assert list(MOVES.items()) == [("up", (0, 1)), ("down", (0, -1)), ("left", (-1, 0)), ("right", (1, 0))]


def test_to_json_key_order_and_lists(example_world):
    assert json.dumps(example_world.to_json()) == json.dumps(_json())


def test_key_ignores_obstacle_order(example_world):
    swapped = World.from_json(_json(wall=[[2, 2], [1, 1]]))
    assert swapped.key() == example_world.key()
    assert swapped != example_world  # the record keeps the given order: it is what the text lists


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"world_size_x": 1}, "size_x=1 is too small; allowed: 2 or more"),
        ({"world_size_y": 0}, "size_y=0 is too small"),
        ({"world_size_x": "4"}, "world_size_x must be an integer"),
        ({"start": [-1, 0]}, "start (-1, 0) is outside the grid"),
        ({"goal": [4, 2]}, "goal (4, 2) is outside the grid"),
        ({"start": [1, 1]}, "start (1, 1) is on a wall"),
        ({"goal": [3, 0]}, "goal (3, 0) is on a pit"),
        ({"wall": [[1, 1], [5, 5]]}, "wall (5, 5) is outside the grid"),
        ({"pit": [[3, 0], [0, 3]]}, "pit (0, 3) is outside the grid"),
        ({"wall": [[1, 1], [2, 2], [1, 1]]}, "wall (1, 1) duplicates a wall"),
        ({"pit": [[3, 0], [3, 0]]}, "pit (3, 0) duplicates a pit"),
        ({"pit": [[3, 0], [2, 2]]}, "pit (2, 2) duplicates a wall"),
        ({"wall": [[1, 1], [2, 2], [2, 0], [1, 2]]}, "unreachable"),
        ({"wall": [[2, 2]]}, "more than one shortest path"),
        ({"goal": [0, 0]}, "must differ"),
        ({"wall": [[1]]}, "wall must be an [x, y] pair"),
        ({"pit": "none"}, "pit must be a list"),
    ],
)
def test_validation_errors(changes, message):
    with pytest.raises(WorldError, match=message.replace("(", r"\(").replace(")", r"\)").replace("[", r"\[")):
        World.from_json(_json(**changes))


def test_world_error_is_value_error():
    assert issubclass(WorldError, ValueError)


@pytest.mark.parametrize("obj", [None, [], {"q": {}}, {"question": {"world_size_x": 4}}])
def test_schema_errors(obj):
    with pytest.raises(WorldError):
        World.from_json(obj)


def test_missing_keys_are_listed():
    obj = _json()
    del obj["question"]["goal"]
    with pytest.raises(WorldError, match="missing keys \\['goal'\\]"):
        World.from_json(obj)


def test_load_names_file_and_line(tmp_path, example_world):
    path = tmp_path / "worlds.jsonl"
    good = json.dumps(example_world.to_json())
    path.write_text(good + "\n" + good + "\n{not json\n")
    with pytest.raises(WorldError, match=f"{path}:3"):
        load_worlds(path)
    path.write_text(good + "\n" + json.dumps(_json(world_size_x=1)) + "\n")
    with pytest.raises(WorldError, match=f"{path}:2: size_x=1"):
        load_worlds(path)


def test_save_load_round_trip(tmp_path, example_world):
    path = tmp_path / "worlds.jsonl"
    other = World.from_json(_json(wall=[[2, 2], [1, 1]]))
    save_worlds(path, [example_world, other])
    assert load_worlds(path) == [example_world, other]


def test_pickle_keeps_the_world(example_world):
    import pickle

    again = pickle.loads(pickle.dumps(example_world))
    assert again == example_world and again.shortest_path() == example_world.shortest_path()


def test_json_input_is_not_mutated(example_world):
    obj = _json()
    before = copy.deepcopy(obj)
    World.from_json(obj)
    assert obj == before


def test_paper_file_loads_and_round_trips(paper_worlds, paper_test_file):
    lines = paper_test_file.read_text().splitlines()
    assert len(paper_worlds) == len(lines) == 3000
    for world, line in zip(paper_worlds, lines):
        assert json.dumps(world.to_json()) == line


def test_paper_worlds_are_corner_to_corner_trees(paper_worlds):
    for world in paper_worlds:
        assert world.start == (world.x0, world.y0) and world.goal == (world.x1, world.y1)
        assert free_cells_form_a_tree(world)


def test_paper_up_right_only_share(paper_worlds):
    """docs/spec.md §1 quirk: about 55% of the paper's test worlds are solvable with up/right moves only."""
    share = sum(world_stats(w).up_right_only for w in paper_worlds) / len(paper_worlds)
    print(f"paper test worlds solvable with up/right only: {share:.1%}")
    assert 0.50 <= share <= 0.60


@given(worlds())
def test_generated_worlds_have_exactly_one_shortest_path(world):
    assert _count_shortest_paths(world) == 1
    path = world.shortest_path()
    assert path[0] == world.start and path[-1] == world.goal
    assert all(world.is_free(c) for c in path)
    assert len(world.optimal_moves()) == len(path) - 1


@given(worlds())
def test_json_round_trip(world):
    assert World.from_json(json.loads(json.dumps(world.to_json()))) == world


def test_step_and_move_between():
    assert step((2, 3), "left") == (1, 3)
    assert move_between((2, 3), (2, 4)) == "up"
    with pytest.raises(ValueError, match="unknown move 'north'; allowed: up, down, left, right"):
        step((0, 0), "north")
    with pytest.raises(ValueError, match="not neighbours"):
        move_between((0, 0), (1, 1))
