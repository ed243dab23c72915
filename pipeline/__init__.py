"""Cognitive-map planning in Textualized Gridworld. The top level exposes the pure domain core only."""

from pipeline.core.texts import conversation
from pipeline.core.world import World

__all__ = ["World", "conversation"]
