"""The report's fixtures: the synthetic store (see store.py) and the report built from it, once for the package."""

from __future__ import annotations

import pytest

from pipeline.report import build

from .store import FWD_MD_WINS, FWD_NM_WINS, Store


@pytest.fixture(scope="package")
def store(tmp_path_factory):
    """Eleven job runs, with a superseded, a FAILED, a two-seed, a shared-eval and an episode-less one."""
    s = Store(tmp_path_factory.mktemp("store"))
    s.job("optimal", "fwd", "marking-deadend", wins=set(range(5)))             # superseded below
    s.job("optimal", "fwd", "marking-deadend", wins=FWD_MD_WINS,
          curve=[(100, 0.1), (200, 0.5), (300, 0.7)])
    s.job("optimal", "fwd", "marking-deadend", wins=set(), status="FAILED")   # ignored
    s.job("optimal", "fwd", "no-marking", wins=FWD_NM_WINS)
    s.job("optimal", "bwd", "cot", wins=set(range(10)), curve=[(100, 0.05), (300, 0.2)])
    s.job("reachable", "bwd", "marking-deadend", 0, wins=set(range(30)),
          curve=[(100, 0.3), (300, 0.8)])
    s.job("reachable", "bwd", "marking-deadend", 1, wins=set(range(34)),
          curve=[(100, 0.4), (300, 0.9)])
    s.job("reachable", "bwd", "dfs", wins=set(range(36)))
    _, shared = s.job("reachable", "fwd", "none", wins=set(range(12)))
    s.job("reachable", "bwd", "none", eval_run=shared)                       # reused eval run
    s.job("reachable", "fwd", "no-all", artifact=False)                      # eval without episodes
    return s


@pytest.fixture(scope="package")
def built(store, tmp_path_factory):
    """The report of ``store`` (with its report run), and the store."""
    out = tmp_path_factory.mktemp("report")
    return build.build_report(store.uri, "cogmap", out), store
