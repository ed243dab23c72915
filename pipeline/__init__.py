"""Cognitive-map planning in Textualized Gridworld. The top level exposes the pure domain core only."""

from pipeline.texts import conversation
from pipeline.world import World

__all__ = ["World", "conversation"]
