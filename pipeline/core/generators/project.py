"""The project's generator ("project"): the paper's recipe (docs/spec.md §1), but a tree search that cuts
the goal off is started again rather than backtracked (the paper's search is `generators.paper`). With
``GeneratorConfig.deep`` (not in the paper) a fraction of its worlds are deep: the tree grows from any cell
until nothing more can join, and the start and the goal are the two ends of its longest path."""

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
    # No draw for the choice when deep is 0: the paper's worlds come from the same stream as before it existed.
    if cfg.deep and rng.random() < cfg.deep:
        tree, start, goal = _deep_tree(rng, size_x, size_y)
    else:
        tree, start, goal = None, 0, size_x * size_y - 1
        while tree is None:
            # The goal gets walled in by the tree in some draws: grow again, the stream continuing.
            tree = _grow_tree(rng, size_x, size_y, start, goal)
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
        start=(x0 + start // size_y, y0 + start % size_y),
        goal=(x0 + goal // size_y, y0 + goal % size_y),
    )


def _deep_tree(rng: random.Random, size_x: int, size_y: int) -> tuple[bytearray, int, int]:
    """(tree mask, start, goal): a tree grown from a random cell until no cell can join, and the two ends of
    its longest path (a farthest cell from the seed, then a farthest cell from that one: the tree's
    diameter), in a random order."""
    seed = int(rng.random() * size_x * size_y)
    tree = _grow_tree(rng, size_x, size_y, seed, goal=None)
    one = _farthest(rng, tree, size_x, size_y, seed)
    other = _farthest(rng, tree, size_x, size_y, one)
    return (tree, one, other) if rng.random() < 0.5 else (tree, other, one)


def _farthest(rng: random.Random, tree: bytearray, size_x: int, size_y: int, origin: int) -> int:
    """A tree cell at the greatest distance from ``origin`` along the tree (drawn among the ties)."""
    neighbours = neighbour_table(size_x, size_y)
    depth, order = {origin: 0}, [origin]
    for i in order:
        for j in neighbours[i]:
            if tree[j] and j not in depth:
                depth[j] = depth[i] + 1
                order.append(j)
    deepest = [i for i in order if depth[i] == depth[order[-1]]]
    return deepest[int(rng.random() * len(deepest))]


def _grow_tree(rng: random.Random, size_x: int, size_y: int, start: int, goal: int | None) -> bytearray | None:
    """Tree cells (column-major mask, cells by index) grown from ``start`` until ``goal`` joins, or None if the
    goal got cut off; with ``goal=None``, until no cell can join.

    A cell joins only while it touches exactly one tree cell, which keeps the free cells a tree and
    so the shortest path unique.
    """
    n = size_x * size_y
    tree = bytearray(n)
    # Tree neighbours per cell. A cell is put on the frontier list when this first becomes 1, so it
    # is listed once; tree cells only ever go above 1, so they are never listed again.
    touching = bytearray(n)
    neighbours = neighbour_table(size_x, size_y)
    random_float = rng.random
    frontier = [start]
    touching[start] = 1  # the start seeds the list as if it touched the tree once
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
        if goal is not None and touching[goal] > 1:
            return None
    return tree if goal is None else None
