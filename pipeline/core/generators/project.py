"""The project's generator ("project"): the paper's recipe (docs/spec.md §1), but a tree search that cuts
the goal off is started again rather than backtracked (the paper's search is `generators.paper`)."""

from __future__ import annotations

import random

from pipeline.core.generators.base import GeneratorConfig, neighbour_table, register
from pipeline.core.world import Cell, World


@register("project")
def sample_world_project(rng: random.Random, cfg: GeneratorConfig) -> World:
    """One world: size, offset and p_pit drawn once, then a random tree grown until it holds the goal."""
    size_x = rng.randint(*cfg.size_x)
    size_y = rng.randint(*cfg.size_y)
    x0 = rng.randint(0, cfg.frame - size_x)
    y0 = rng.randint(0, cfg.frame - size_y)
    p_pit = rng.uniform(*cfg.p_pit)
    tree = None
    while tree is None:
        # The goal gets walled in by the tree in some draws: grow again, the stream continuing.
        tree = _grow_tree(rng, size_x, size_y)
    obstacles = [i for i, in_tree in enumerate(tree) if not in_tree]
    # Shuffled like the paper's own files, whose obstacle lists are in no spatial order.
    rng.shuffle(obstacles)
    walls: list[Cell] = []
    pits: list[Cell] = []
    for i in obstacles:
        cell = (x0 + i // size_y, y0 + i % size_y)
        (pits if rng.random() < p_pit else walls).append(cell)
    return World(
        size_x=size_x,
        size_y=size_y,
        x0=x0,
        y0=y0,
        walls=tuple(walls),
        pits=tuple(pits),
        start=(x0, y0),
        goal=(x0 + size_x - 1, y0 + size_y - 1),
    )


def _grow_tree(rng: random.Random, size_x: int, size_y: int) -> bytearray | None:
    """Tree cells (column-major mask, start = index 0, goal = last) or None if the goal got cut off.

    A cell joins only while it touches exactly one tree cell, which keeps the free cells a tree and
    so the shortest path unique.
    """
    n = size_x * size_y
    goal = n - 1
    tree = bytearray(n)
    # Tree neighbours per cell. A cell is put on the frontier list when this first becomes 1, so it
    # is listed once; tree cells only ever go above 1, so they are never listed again.
    touching = bytearray(n)
    neighbours = neighbour_table(size_x, size_y)
    random_float = rng.random
    frontier = [0]
    touching[0] = 1  # the start seeds the list as if it touched the tree once
    while frontier:
        # Uniform pick (random() is several times cheaper than randrange in this hot loop);
        # stale entries, now touching two tree cells, are dropped lazily.
        k = int(random_float() * len(frontier))
        i = frontier[k]
        frontier[k] = frontier[-1]
        frontier.pop()
        if touching[i] != 1:
            continue
        tree[i] = 1
        if i == goal:
            return tree
        for j in neighbours[i]:
            touching[j] += 1
            if touching[j] == 1:
                frontier.append(j)
        if touching[goal] > 1:
            return None
    return None
