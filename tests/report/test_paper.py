"""The paper's numbers the report prints beside ours."""

from __future__ import annotations

from pipeline.report import paper


def test_paper_numbers_match_spec():
    spec = {  # docs/spec.md §5, (mode, variant): (FWD, BWD)
        ("optimal", "none"): (0.190, 0.190), ("optimal", "cot"): (0.252, 0.265),
        ("optimal", "marking-deadend"): (0.585, 0.705), ("optimal", "no-marking"): (0.618, 0.765),
        ("reachable", "none"): (0.321, 0.321), ("reachable", "cot"): (0.339, 0.287),
        ("reachable", "marking-deadend"): (0.854, 0.885), ("reachable", "no-marking"): (0.816, 0.724),
        ("optimal", "no-all-no-backtrack"): (0.295, 0.296), ("optimal", "no-all"): (0.290, 0.277),
        ("reachable", "no-all-no-backtrack"): (0.416, 0.394), ("reachable", "no-all"): (0.345, 0.283),
        ("optimal", "no-marking-no-backtrack"): (0.528, 0.406),
        ("optimal", "no-backtrack"): (0.516, 0.423),
        ("reachable", "no-marking-no-backtrack"): (0.672, 0.739),
        ("reachable", "no-backtrack"): (0.624, 0.852), ("reachable", "dfs"): (0.945, 0.945)}
    assert paper.PAPER_SUCCESS == spec
