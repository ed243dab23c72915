"""Shared fixtures and hypothesis strategies for the domain-core tests."""

from __future__ import annotations

import os
import random
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from pipeline.core.generators import GeneratorConfig, sample_world
from pipeline.core.world import World, load_worlds

ROOT = Path(__file__).resolve().parents[1]   # the repository
TOY = ("data=toy", "model=toy", "train=toy", "eval=toy")


def compose_job(root, *overrides, name: str = "config", config_dir: Path | None = None, toy: bool = True,
                return_hydra_config: bool = False):
    """THE way tests compose a job's config: the toy presets (unless ``toy=False``), a store under ``root``
    (unless None), then ``overrides``; ``name`` and ``config_dir`` pick another primary config (a sweep)."""
    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from pipeline.workflow.config import register_configs

    register_configs()
    GlobalHydra.instance().clear()
    with initialize_config_dir(str(config_dir or ROOT / "conf"), version_base="1.3"):
        prefix = [*(TOY if toy else ()), *([f"tracking.root={root}"] if root is not None else [])]
        return compose(name, overrides=[*prefix, *overrides], return_hydra_config=return_hydra_config)


def _paper_test() -> Path | None:
    """The paper's released test worlds: $COGMAP_PAPER_TEST (CI points it at its local copy), else the copy a
    fetch left in the cache (pipeline.workflow.paper_data). Tests that need it skip, naming both, without."""
    from pipeline.workflow.paper_data import cached_path

    candidates = [os.environ.get("COGMAP_PAPER_TEST"), cached_path("test")]
    return next((Path(c) for c in candidates if c and Path(c).is_file()), None)


PAPER_TEST = _paper_test()
# Meta-Llama-3-8B's tokenizer, no weights (its README says where it comes from and under which licence).
LLAMA3_TOKENIZER = ROOT / "tests" / "fixtures" / "llama3_tokenizer"

# World generation dominates example time; no deadline so a slow CI box does not flake.
settings.register_profile(
    "core", max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile("core")


def worlds(max_size: int = 9) -> st.SearchStrategy[World]:
    """Generated worlds of sides 2..max_size, drawn through the real generator from a random seed."""
    cfg = GeneratorConfig(size_x=(2, max_size), size_y=(2, max_size))
    return st.integers(0, 2**32).map(lambda seed: sample_world(random.Random(seed), cfg))


@pytest.fixture
def example_world() -> World:
    """The paper's worked example (docs/spec.md §2): grid (0, 0)-(3, 2), pit (3, 0), walls (1, 1), (2, 2)."""
    return World(
        size_x=4,
        size_y=3,
        x0=0,
        y0=0,
        walls=((1, 1), (2, 2)),
        pits=((3, 0),),
        start=(0, 0),
        goal=(3, 2),
    )


@pytest.fixture(scope="session")
def paper_test_file() -> Path:
    """Path of the paper's released test file (skips, naming it, where it is absent)."""
    if PAPER_TEST is None:
        pytest.skip("the paper's test file is not available: set COGMAP_PAPER_TEST to a copy, or fetch it "
                    "(python -m pipeline.workflow.paper_data test)")
    return PAPER_TEST


@pytest.fixture(scope="session")
def llama3_tokenizer_dir() -> Path:
    """The folder of the real Llama-3 tokenizer. Without its files the tests that need it skip, naming them;
    in CI (``CI`` set) they fail instead, so CI always runs them."""
    missing = [name for name in ("tokenizer.json", "tokenizer_config.json") if not (LLAMA3_TOKENIZER / name).is_file()]
    if missing:
        reason = (f"the Llama-3 tokenizer fixture lacks {', '.join(missing)} in {LLAMA3_TOKENIZER.relative_to(ROOT)} "
                  "(its README says how to rebuild it)")
        if os.environ.get("CI"):
            pytest.fail(reason)
        pytest.skip(reason)
    return LLAMA3_TOKENIZER


@pytest.fixture(scope="session")
def llama3_tokenizer(llama3_tokenizer_dir):
    """Meta-Llama-3-8B's tokenizer as transformers loads it from its model folder (shared: do not modify)."""
    from transformers import AutoTokenizer

    return AutoTokenizer.from_pretrained(llama3_tokenizer_dir, local_files_only=True)


@pytest.fixture(scope="session")
def tiny_llama3_dir(llama3_tokenizer_dir, tmp_path_factory) -> Path:
    """A saved, randomly initialised Llama of 2 layers of 32 over the real Llama-3 tokenizer (its 128,256
    tokens, no pad token: a `model=hf` path shaped as Meta-Llama-3-8B's folder is, at toy size)."""
    from transformers import AutoTokenizer

    from pipeline.lm.model_settings import ModelSettings
    from pipeline.lm.models import build_scratch_model

    target = tmp_path_factory.mktemp("tiny-llama3")
    tokenizer = AutoTokenizer.from_pretrained(llama3_tokenizer_dir, local_files_only=True)
    settings = ModelSettings(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, max_length=8192)
    build_scratch_model(tokenizer, settings).save_pretrained(target)
    tokenizer.save_pretrained(target)
    return target


@pytest.fixture(scope="session")
def paper_worlds(paper_test_file) -> list[World]:
    """The paper's released test set, loaded once per session."""
    return load_worlds(paper_test_file)


# docs/spec.md §2-3 golden strings for the worked example, character for character.
GOLDEN_TURN_3 = (
    "Grid is from (0, 0) to (3, 2). Goal: (3, 2)\nCurrent: (0, 0)\nThe pit is at (3, 0). The wall is at (1, 1), "
    "and (2, 2).\nCurrent:\n(0, 0)\nPossible:\n(0, 1)\nup\n(1, 0)\nright"
)
GOLDEN_FWD_MARKING_DEADEND = (
    "Thought:\nStep 1:\n(0, 1)\nup\n(0, -1)\ncut\n(-1, 0)\ncut\n(1, 0)\nright\nStep 2:\n(0, 2)\nup\n(0, 0)\ncut\n"
    "(-1, 1)\ncut\n(1, 1)\ncut\n(1, 1)\ncut\n(1, -1)\ncut\n(0, 0)\ncut\n(2, 0)\nright\nStep 3:\n(0, 3)\ncut\n"
    "(0, 1)\ncut\n(-1, 2)\ncut\n(1, 2)\nright\n(2, 1)\nup\n(2, -1)\ncut\n(1, 0)\ncut\n(3, 0)\ncut\nStep 4:\n"
    "(1, 3)\ncut\n(1, 1)\ncut\n(0, 2)\ncut\n(2, 2)\ncut\n(2, 2)\ncut\n(2, 0)\ncut\n(1, 1)\ncut\n(3, 1)\nright\n"
    "Step 5:\n(3, 2)\nup\n(3, 0)\ncut\n(2, 1)\ncut\n(4, 1)\ncut\nBacktrack:\n(3, 2)\nup\n(3, 1)\nright\n(2, 1)\n"
    "up\n(2, 0)\nright\n(1, 0)\nright\n(0, 0)\nPlan:\nright\nright\nup\nright\nup"
)
GOLDEN_BWD_NO_ALL = (
    "Thought:\nStep 1:\n(3, 1)\nup\nStep 2:\n(2, 1)\nright\nStep 3:\n(2, 0)\nup\nStep 4:\n(1, 0)\nright\n"
    "Step 5:\n(0, 0)\nright\nBacktrack:\n(0, 0)\nright\n(1, 0)\nright\n(2, 0)\nup\n(2, 1)\nright\n(3, 1)\nup\n"
    "(3, 2)\nPlan:\nright\nright\nup\nright\nup"
)


@pytest.fixture
def golden() -> dict[str, str]:
    """The worked example's golden texts by name."""
    return {
        "turn_3": GOLDEN_TURN_3,
        "fwd_marking_deadend": GOLDEN_FWD_MARKING_DEADEND,
        "bwd_no_all": GOLDEN_BWD_NO_ALL,
    }


def free_cells_form_a_tree(world: World) -> bool:
    """Connected (validation checks reachability) and n-1 edges between n free cells: a tree."""
    free = [
        (x, y)
        for x in range(world.x0, world.x1 + 1)
        for y in range(world.y0, world.y1 + 1)
        if world.is_free((x, y))
    ]
    edges = sum(world.is_free((x + 1, y)) + world.is_free((x, y + 1)) for x, y in free)
    return edges == len(free) - 1
