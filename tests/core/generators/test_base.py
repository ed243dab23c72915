"""What every generator shares: the config's checks, the registry, and the driver's determinism, worker
independence, dedup/exclusion and budget."""

from __future__ import annotations

import json
import random

import pytest

from pipeline.core.checks import SettingError
from pipeline.core.generators import GENERATORS, GeneratorConfig, generate_worlds, sample_world
from pipeline.core.generators.base import register
from pipeline.core.generators.paper import sample_world_paper
from pipeline.core.generators.project import sample_world_project
from pipeline.core.world import World


def _dump(ws: list[World]) -> str:
    return "\n".join(json.dumps(w.to_json()) for w in ws)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"size_x": (1, 10)}, "size_x=\\(1, 10\\)"),
        ({"size_y": (5, 4)}, "size_y=\\(5, 4\\)"),
        ({"size_x": (2, 21)}, "frame \\(20\\)"),
        ({"size_y": (2, 12), "frame": 10}, "frame \\(10\\)"),
        ({"size_x": (2,)}, "size_x=\\(2,\\) is not allowed; expected \\[min, max\\]"),
        ({"p_pit": (-0.1, 0.5)}, "p_pit"),
        ({"p_pit": (0.5, 1.5)}, "0 <= min <= max <= 1"),
        ({"generator": "pape"}, "generator='pape' is not allowed; expected one of project, paper"),
    ],
)
def test_config_validation(kwargs, message):
    with pytest.raises(SettingError, match=message):
        GeneratorConfig(**kwargs)


def test_the_registry_names_each_generator_and_refuses_a_name_twice():
    assert GENERATORS == {"project": sample_world_project, "paper": sample_world_paper}
    cfg = GeneratorConfig(size_x=(2, 6), size_y=(2, 6), generator="paper")
    assert sample_world(random.Random(4), cfg) == sample_world_paper(random.Random(4), cfg)
    with pytest.raises(ValueError, match="'paper' is already registered"):
        register("paper")(sample_world_project)


def test_same_seed_same_worlds_byte_for_byte():
    assert _dump(generate_worlds(200, seed=7)) == _dump(generate_worlds(200, seed=7))
    assert _dump(generate_worlds(200, seed=7)) != _dump(generate_worlds(200, seed=8))
    assert _dump(generate_worlds(200, seed=7)) != _dump(generate_worlds(200, seed=7, split="test"))


def test_prefix_stability():
    """Asking for more worlds extends the list: candidate i never depends on n."""
    assert generate_worlds(300, seed=3)[:100] == generate_worlds(100, seed=3)


def test_workers_do_not_change_the_result():
    cfg = GeneratorConfig(size_x=(2, 12), size_y=(2, 12))
    assert _dump(generate_worlds(700, seed=1, cfg=cfg, workers=1)) == _dump(
        generate_worlds(700, seed=1, cfg=cfg, workers=2)
    )


def test_no_duplicates_even_when_the_space_is_tiny():
    # 2x2 worlds at a fixed offset: 2 trees x 2 obstacle kinds = 4 distinct worlds only.
    cfg = GeneratorConfig(size_x=(2, 2), size_y=(2, 2), frame=2)
    ws = generate_worlds(4, seed=0, cfg=cfg)
    assert len({w.key() for w in ws}) == 4


def test_exclude_is_respected():
    test = generate_worlds(300, seed=0, split="test")
    excluded = {w.key() for w in test}
    train = generate_worlds(2000, seed=0, split="train", exclude=excluded)
    assert len(train) == 2000
    assert len({w.key() for w in train}) == 2000
    assert not excluded & {w.key() for w in train}
    # And exclusion bites: worlds a plain run would return are skipped.
    plain = generate_worlds(100, seed=5)
    dropped = {w.key() for w in plain[:50]}
    again = generate_worlds(100, seed=5, exclude=dropped)
    assert again[:50] == plain[50:]


def test_bad_arguments():
    with pytest.raises(ValueError, match="workers"):
        generate_worlds(3, seed=0, workers=0)
    assert generate_worlds(0, seed=0) == []


def test_asking_for_more_distinct_worlds_than_exist_fails_naming_the_numbers():
    # 2 x 2 worlds in a 2 x 2 frame: two trees, each with one obstacle cell (wall or pit): 4 worlds.
    cfg = GeneratorConfig(size_x=(2, 2), size_y=(2, 2), frame=2)
    assert len(generate_worlds(4, 0, cfg)) == 4
    with pytest.raises(ValueError, match="found only 4 of n=5 distinct train worlds"):
        generate_worlds(5, 0, cfg)
