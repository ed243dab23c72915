"""The paper's numbers: its success rates, to print beside ours (docs/spec.md, section 5)."""

from __future__ import annotations

import math

from pipeline.core.variants import DIRECTIONS

# docs/spec.md, section 5: the paper's success rates, (mode, variant) -> (FWD, BWD). NONE is direction-independent
# (one number printed in both columns); DFS (Table 3) is reachable-only and direction-independent.
PAPER_SUCCESS: dict[tuple[str, str], tuple[float, float]] = {
    ("optimal", "none"): (0.190, 0.190),
    ("optimal", "cot"): (0.252, 0.265),
    ("optimal", "marking-deadend"): (0.585, 0.705),
    ("optimal", "no-marking"): (0.618, 0.765),
    ("reachable", "none"): (0.321, 0.321),
    ("reachable", "cot"): (0.339, 0.287),
    ("reachable", "marking-deadend"): (0.854, 0.885),
    ("reachable", "no-marking"): (0.816, 0.724),
    ("optimal", "no-all-no-backtrack"): (0.295, 0.296),
    ("optimal", "no-all"): (0.290, 0.277),
    ("reachable", "no-all-no-backtrack"): (0.416, 0.394),
    ("reachable", "no-all"): (0.345, 0.283),
    ("optimal", "no-marking-no-backtrack"): (0.528, 0.406),
    ("optimal", "no-backtrack"): (0.516, 0.423),
    ("reachable", "no-marking-no-backtrack"): (0.672, 0.739),
    ("reachable", "no-backtrack"): (0.624, 0.852),
    ("reachable", "dfs"): (0.945, 0.945),
}


def paper_success(mode: str, variant: str, direction: str) -> float:
    """The paper's success rate for a cell (docs/spec.md §5), nan where the paper has none."""
    pair = PAPER_SUCCESS.get((mode, variant))
    if pair is None:
        return math.nan
    if direction in DIRECTIONS:
        return pair[DIRECTIONS.index(direction)]
    return pair[0] if pair[0] == pair[1] else math.nan  # direction-independent rows only
