"""Small statistics for the report: Wilson intervals, McNemar's test, several seeds in one cell.

Pure functions of counts (numpy/scipy only), so they are tested against textbook values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

# The normal distribution's 97.5% quantile, scipy.stats.norm.ppf(0.975) (a test checks it): a constant, so that
# importing this module (a job does, through the report's Hydra callback) does not import scipy (about 0.5 s).
Z95 = 1.959963984540054


def wilson_interval(successes: int, n: int, z: float = Z95) -> tuple[float, float]:
    """The Wilson score interval for a binomial rate (95% by default); ``(nan, nan)`` when ``n == 0``."""
    if n <= 0:
        return (math.nan, math.nan)
    if not 0 <= successes <= n:
        raise ValueError(f"successes={successes} outside 0..n={n}")
    p = successes / n
    z2 = z * z
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = z / (1 + z2 / n) * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    # Clamp the rounding error at the ends (k=0 gives exactly 0 in exact arithmetic).
    return (max(0.0, centre - half), min(1.0, centre + half))


@dataclass(frozen=True)
class McNemar:
    """McNemar's exact test on paired binary outcomes of A and B over the same items."""

    n_pairs: int
    both: int        # A and B succeed
    only_a: int      # A succeeds, B fails
    only_b: int      # B succeeds, A fails
    neither: int
    p_value: float   # two-sided exact binomial on the discordant pairs (1.0 with none)


def mcnemar_exact(only_a: int, only_b: int) -> float:
    """Two-sided exact McNemar p-value: a binomial test of ``only_a`` out of ``only_a + only_b`` at 1/2.

    The exact form (not the chi-square approximation) because cells of a few hundred worlds often have
    fewer than 25 discordant pairs.
    """
    from scipy.stats import binomtest

    discordant = only_a + only_b
    if discordant == 0:
        return 1.0
    return float(binomtest(only_a, discordant, 0.5, alternative="two-sided").pvalue)


def mcnemar(a: Sequence[bool], b: Sequence[bool]) -> McNemar:
    """McNemar's exact test for two aligned sequences of outcomes (the same items in the same order)."""
    if len(a) != len(b):
        raise ValueError("paired outcomes must have the same length")
    both = sum(1 for x, y in zip(a, b) if x and y)
    only_a = sum(1 for x, y in zip(a, b) if x and not y)
    only_b = sum(1 for x, y in zip(a, b) if y and not x)
    neither = len(a) - both - only_a - only_b
    return McNemar(len(a), both, only_a, only_b, neither, mcnemar_exact(only_a, only_b))


@dataclass(frozen=True)
class SeededRate:
    """A success rate over one or more seeds.

    ``rate`` is the mean of the per-seed rates; ``ci_low``/``ci_high`` the Wilson interval of all episodes
    pooled over seeds (it ignores seed-to-seed variance, hence ``seed_min``/``seed_max``/``seed_sd``).
    """

    n_seeds: int
    successes: int
    n: int
    rate: float
    ci_low: float
    ci_high: float
    seed_min: float
    seed_max: float
    seed_sd: float   # sample standard deviation of the per-seed rates (nan for one seed)


def seeded_rate(per_seed: Sequence[tuple[int, int]]) -> SeededRate:
    """Combine ``(successes, n)`` per seed into a :class:`SeededRate` (seeds with ``n == 0`` are dropped)."""
    counts = [(k, n) for k, n in per_seed if n > 0]
    if not counts:
        nan = math.nan
        return SeededRate(0, 0, 0, nan, nan, nan, nan, nan, nan)
    rates = [k / n for k, n in counts]
    k_all = sum(k for k, _ in counts)
    n_all = sum(n for _, n in counts)
    mean = sum(rates) / len(rates)
    sd = (math.sqrt(sum((r - mean) ** 2 for r in rates) / (len(rates) - 1))
          if len(rates) > 1 else math.nan)
    low, high = wilson_interval(k_all, n_all)
    return SeededRate(len(counts), k_all, n_all, mean, low, high, min(rates), max(rates), sd)
