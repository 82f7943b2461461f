"""Percentiles of a run's times in bounded memory: counts in log-spaced bins, as HdrHistogram keeps latencies.

A daemon runs for hours at up to 144 Hz: keeping every frame's times grows without bound, and the `stats`
topic would sort all of them each second. Here each value lands in one of a fixed number of bins whose
width is 0.23% of the value (1000 per decade), and the exact minimum and maximum are kept; a percentile is
the geometric middle of the bin holding its nearest-rank value, within [min, max], so it is within 0.12%
(below 1 us it is the minimum, beyond 10^6 ms the maximum). The gaze error at photon time is kept so too, in
degrees (below 0.001 degrees, the minimum).
"""

from __future__ import annotations

import math
from array import array

import numpy as np

BINS_PER_DECADE = 1000
LOW_MS = 1e-3  # 1 us; a smaller value (0 included) counts in the first bin, and the minimum stays exact
DECADES = 9  # to 10^6 ms (17 min); a larger value counts in the last bin, and the maximum stays exact
BINS = BINS_PER_DECADE * DECADES
_SCALE = BINS_PER_DECADE / math.log(10.0)


class Histogram:
    """Non-negative values (ms, or degrees): their count, exact min and max, and percentiles to within 0.12%."""

    __slots__ = ("counts", "n", "min", "max")

    def __init__(self) -> None:
        self.counts = array("q", bytes(8 * BINS))  # a count costs a C increment, not a numpy scalar's boxing
        self.n = 0
        self.min = math.inf
        self.max = -math.inf

    def add(self, value: float) -> None:
        if not value >= 0.0:  # NaN included: a measured time is never negative or undefined
            raise ValueError(f"a time must be a non-negative number, got {value}")
        at = int(math.log(value / LOW_MS) * _SCALE) if value > LOW_MS else 0
        self.counts[min(at, BINS - 1)] += 1
        self.n += 1
        self.min = min(self.min, value)
        self.max = max(self.max, value)

    def copy(self) -> Histogram:
        out = Histogram()
        out.counts = array("q", self.counts)
        out.n, out.min, out.max = self.n, self.min, self.max
        return out

    def percentiles(self, keys: tuple[int, ...] = (50, 95, 99)) -> dict[str, float | None]:
        """{p50, p95, p99, max} rounded to microseconds (all None when there are no values)."""
        if not self.n:
            return {**{f"p{k}": None for k in keys}, "max": None}
        ranks = [max(1, math.ceil(k / 100 * self.n)) for k in keys]
        bins = np.searchsorted(np.cumsum(np.frombuffer(self.counts, dtype=np.int64)), ranks)
        out = {}
        for k, at in zip(keys, bins, strict=True):
            if at == 0:
                value = self.min  # below 1 us: within the rounding
            elif at == BINS - 1:
                value = self.max  # beyond 10^6 ms
            else:
                value = min(max(LOW_MS * 10.0 ** ((at + 0.5) / BINS_PER_DECADE), self.min), self.max)
            out[f"p{k}"] = round(float(value), 3)
        return {**out, "max": round(self.max, 3)}
