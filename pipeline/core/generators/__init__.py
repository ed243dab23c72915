"""World generators, seeded per world (docs/spec.md §1): the shared settings, registry and driver (`base`),
the project's generator (`project`), the paper's (`paper`), and the statistics of a world (`stats`).

Importing the package registers every generator; a new one is a module that registers itself with
`base.register`, imported here.
"""

# Registered in this order, which is the order messages list them in: the default first.
from pipeline.core.generators import project
from pipeline.core.generators import paper
from pipeline.core.generators.base import (GENERATORS, GeneratorConfig, check_deep, check_ranges, generate_worlds,
                                           sample_world, world_rng)
from pipeline.core.generators.stats import WorldStats, world_stats

__all__ = ["GENERATORS", "GeneratorConfig", "WorldStats", "check_deep", "check_ranges", "generate_worlds",
           "sample_world", "world_rng", "world_stats"]
