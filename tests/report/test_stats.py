"""The report's statistics against closed forms, scipy and hand-computed values."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest
from scipy.stats import binomtest

from pipeline.report.stats import Z95, mcnemar, mcnemar_exact, seeded_rate, wilson_interval


def test_the_95_percent_quantile_is_scipys_and_importing_the_module_leaves_scipy_alone():
    from scipy.stats import norm

    assert Z95 == float(norm.ppf(0.975))
    code = "import sys, pipeline.report.stats; print('scipy.stats' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout == "False\n"


def test_wilson_closed_forms():
    z2 = 1.959963984540054 ** 2
    assert wilson_interval(0, 10) == pytest.approx((0.0, z2 / (10 + z2)))      # (0, 0.27753)
    assert wilson_interval(10, 10) == pytest.approx((10 / (10 + z2), 1.0))    # (0.72247, 1)
    assert wilson_interval(0, 10)[1] == pytest.approx(0.27753, abs=1e-5)
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_wilson_matches_scipy():
    for k, n in ((30, 40), (64, 80), (1, 7), (500, 3000)):
        ci = binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert wilson_interval(k, n) == pytest.approx((ci.low, ci.high), abs=1e-9)


def test_mcnemar_exact_known_values():
    # 2 * P(X <= 4), X ~ Bin(14, 1/2) = 2 * (1 + 14 + 91 + 364 + 1001) / 2**14
    assert mcnemar_exact(4, 10) == pytest.approx(2 * 1471 / 2 ** 14)
    assert mcnemar_exact(10, 4) == pytest.approx(mcnemar_exact(4, 10))
    assert mcnemar_exact(0, 10) == pytest.approx(2 / 2 ** 10)
    assert mcnemar_exact(0, 0) == 1.0
    test = mcnemar([True, True, False, False, True], [True, False, True, False, False])
    assert (test.both, test.only_a, test.only_b, test.neither) == (1, 2, 1, 1)
    assert test.p_value == pytest.approx(1.0)


def test_seeded_rate_means_per_seed_and_pools_interval():
    rate = seeded_rate([(30, 40), (34, 40)])
    assert rate.rate == pytest.approx(0.8)
    assert (rate.successes, rate.n, rate.n_seeds) == (64, 80, 2)
    assert (rate.ci_low, rate.ci_high) == pytest.approx(wilson_interval(64, 80))
    assert (rate.seed_min, rate.seed_max) == pytest.approx((0.75, 0.85))
    assert rate.seed_sd == pytest.approx(math.sqrt(2 * 0.05 ** 2))
    unequal = seeded_rate([(1, 2), (1, 10)])
    assert unequal.rate == pytest.approx(0.3)          # mean of 0.5 and 0.1, not 2/12
    assert seeded_rate([]).n == 0 and math.isnan(seeded_rate([]).rate)
