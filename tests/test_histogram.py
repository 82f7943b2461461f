"""The run report's bounded histograms: percentiles within 0.12% of the exact nearest-rank value, exact
extremes, and the same memory after a million values as after one."""

import math

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

from hmdrt.telemetry.histogram import BINS, BINS_PER_DECADE, Histogram


def nearest_rank(values, k):
    ordered = sorted(values)
    return ordered[max(1, math.ceil(k / 100 * len(ordered))) - 1]


def filled(values):
    h = Histogram()
    for v in values:
        h.add(v)
    return h


@given(st.lists(st.floats(min_value=1e-3, max_value=1e6), min_size=1, max_size=300))
@example([1.0, 2.5])  # 2.5 near its bin's top edge: the middle is 2.497
def test_percentiles_are_within_a_bin_of_the_nearest_rank_value(values):
    out = filled(values).percentiles()
    for k in (50, 95, 99):  # a bin's half-width (in log space: 10^(0.5/1000) - 1 of the value), then the 1 us rounding
        exact = nearest_rank(values, k)
        assert abs(out[f"p{k}"] - exact) <= (10 ** (0.5 / BINS_PER_DECADE) - 1) * exact + 5e-4 + 1e-12
    assert out["max"] == round(max(values), 3)


def test_a_constant_is_reported_exactly_and_extremes_outside_the_bins_stay_exact():
    assert filled([33.333] * 50).percentiles() == {"p50": 33.333, "p95": 33.333, "p99": 33.333, "max": 33.333}
    h = filled([0.0, 0.0, 5e6])  # below the first bin edge and beyond the last
    assert h.percentiles() == {"p50": 0.0, "p95": 5e6, "p99": 5e6, "max": 5e6}
    assert all(type(v) is float for v in h.percentiles().values())  # plain floats, for JSON
    assert filled([]).percentiles() == {"p50": None, "p95": None, "p99": None, "max": None}


def test_memory_is_bounded_and_a_copy_is_independent():
    rng = np.random.default_rng(3)
    values = rng.lognormal(2.3, 0.4, 1_000_000)
    h = Histogram()
    for v in values:
        h.add(float(v))
    assert len(h.counts) == BINS and h.n == 1_000_000
    exact = np.percentile(values, [50, 99], method="inverted_cdf")
    out = h.percentiles()
    assert out["p50"] == pytest.approx(exact[0], rel=1.2e-3) and out["p99"] == pytest.approx(exact[1], rel=1.2e-3)
    copy = h.copy()
    h.add(1e5)
    assert copy.n == 1_000_000 and copy.max < 1e5 and h.max == 1e5


@pytest.mark.parametrize("bad", [-1.0, math.nan])
def test_a_negative_or_undefined_time_is_refused(bad):
    with pytest.raises(ValueError, match="non-negative"):
        Histogram().add(bad)
