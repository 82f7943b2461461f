"""Gaze between tracker and renderer: fixation smoothing (smith2013 section 3.2) and vergence depth
(weier2018 section 3.2)."""

from __future__ import annotations

import math

import numpy as np


class FixationFilter:
    """Smooths tracker noise out of the fixation without lagging behind saccades.

    smith2013 places "an auxiliary smoothing filter" between tracker and renderer because peripheral
    vision is sensitive to the jitter of raw fixations; the paper does not specify it. This one is an
    exponential moving average on the unit gaze direction with weight `alpha` for the new sample,
    which jumps straight to the new sample when it is more than `saccade_deg` away (a saccade), or when
    the blend cancels out (the new sample opposite the fixation, possible with saccade_deg = 180). The
    filter counts samples, not time: a stall between two samples is one step like any other. A gaze that
    is not a finite, non-zero 3-vector raises ValueError and leaves the state as it was.
    """

    def __init__(self, alpha: float = 0.5, saccade_deg: float = 3.0):
        if not 0.0 < alpha <= 1.0:
            raise ValueError("alpha must be in (0, 1]")
        self.alpha = alpha
        self.cos_saccade = math.cos(math.radians(saccade_deg))
        self.state: np.ndarray | None = None

    def __call__(self, gaze: np.ndarray) -> np.ndarray:
        g = np.asarray(gaze, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)) or not np.any(g):
            raise ValueError(f"gaze must be a finite, non-zero 3-vector, got {gaze!r}")
        if self.state is None or float(self.state @ g) < self.cos_saccade:
            self.state = g.copy()
        else:
            blend = self.alpha * g + (1.0 - self.alpha) * self.state
            norm = float(np.linalg.norm(blend))
            self.state = blend / norm if norm > 1e-9 else g.copy()
        return self.state


def vergence_depth(origin_l: np.ndarray, dir_l: np.ndarray, origin_r: np.ndarray, dir_r: np.ndarray) -> float | None:
    """Distance (m) along the mean gaze to where the two eyes' gaze rays pass closest, or None when
    they diverge or are parallel (gaze at infinity)."""
    w0 = np.asarray(origin_l, float) - np.asarray(origin_r, float)
    a, b, c = dir_l @ dir_l, dir_l @ dir_r, dir_r @ dir_r
    d, e = dir_l @ w0, dir_r @ w0
    denom = a * c - b * b
    if denom < 1e-12:
        return None
    s, t = (b * e - c * d) / denom, (a * e - b * d) / denom
    if s <= 0 or t <= 0:
        return None
    midpoint = 0.5 * ((origin_l + s * dir_l) + (origin_r + t * dir_r))
    centre = 0.5 * (np.asarray(origin_l, float) + np.asarray(origin_r, float))
    return float(np.linalg.norm(midpoint - centre))
