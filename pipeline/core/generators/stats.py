"""World statistics: what the report groups results by, computed from a world alone."""

from __future__ import annotations

from dataclasses import dataclass

from pipeline.core.world import World


@dataclass(frozen=True)
class WorldStats:
    """What the report groups results by."""

    size_x: int
    size_y: int
    optimal_length: int
    dead_ends: int
    up_right_only: bool
    interpolated: bool


def world_stats(world: World, train_max: tuple[int, int] = (10, 10)) -> WorldStats:
    """Size, optimal length, dead-end count and the up/right-only and interpolation flags of a world."""
    moves = world.optimal_moves()
    return WorldStats(
        size_x=world.size_x,
        size_y=world.size_y,
        optimal_length=len(moves),
        dead_ends=_count_dead_ends(world),
        up_right_only=set(moves) <= {"up", "right"},
        interpolated=world.size_x <= train_max[0] and world.size_y <= train_max[1],
    )


def _count_dead_ends(world: World) -> int:
    """Leaves (one free neighbour) of the start's component, other than start and goal."""
    blocked, offsets = world.padded, world.offsets()
    ends = {world.index(world.start), world.index(world.goal)}
    seen = {world.index(world.start)}
    stack = list(seen)
    leaves = 0
    while stack:
        i = stack.pop()
        free = [i + o for o in offsets if not blocked[i + o]]
        if len(free) == 1 and i not in ends:
            leaves += 1
        for j in free:
            if j not in seen:
                seen.add(j)
                stack.append(j)
    return leaves
