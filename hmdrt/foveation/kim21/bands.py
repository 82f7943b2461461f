"""kim21's foveation per pixel (kim2021): the band of section 4.1 and its samples per problematic subpixel (section
4.6.2), tau_fov(e) from two C1 quadratic Bezier segments (section 4.6.1) and the smoothing factor alpha(e),
piecewise linear (section 4.7), derived from the eccentricity map once per change of frustum, gaze or parameters."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.errors import ConfigError
from hmdrt.foveation.kim21.params import Kim21Params
from hmdrt.kernels.jit import inline, kernel, serial


def bezier_controls(p: Kim21Params) -> np.ndarray:
    """Control points of tau_fov's two quadratic Bezier segments, as [x0, x1, x2, y0, y1, y2] x 2.

    C1 runs from (0, tau_0) to (e_f, tau_f) with slope 0 then tau_f'; C2 from (e_f, tau_f) to
    (e_np, tau_np) with slope tau_f' then 0. Each middle control point is where the end tangents
    cross; it must lie between the end points in e so that tau_fov is a function of e.
    """

    def middle(x0: float, y0: float, s0: float, x2: float, y2: float, s2: float) -> float:
        if y0 == y2:
            return 0.5 * (x0 + x2)  # a flat segment: any middle point on the line
        slope = s2 if s0 == 0.0 else s0
        if slope == 0.0:
            raise ConfigError("tau_f_slope must be positive unless tau_0, tau_f and tau_np are equal")
        return x2 - (y2 - y0) / slope if s0 == 0.0 else x0 + (y2 - y0) / slope

    m1 = middle(0.0, p.tau_0, 0.0, p.e_f, p.tau_f, p.tau_f_slope)
    m2 = middle(p.e_f, p.tau_f, p.tau_f_slope, p.e_np, p.tau_np, 0.0)
    if not (0.0 <= m1 <= p.e_f and p.e_f <= m2 <= p.e_np):
        raise ConfigError(
            f"tau_fov shape (tau_0={p.tau_0}, tau_f={p.tau_f}, tau_f'={p.tau_f_slope}, tau_np={p.tau_np}) "
            "does not give a function of eccentricity: the tangents must meet between the band edges"
        )
    return np.array([0.0, m1, p.e_f, p.tau_0, p.tau_0, p.tau_f, p.e_f, m2, p.e_np, p.tau_f, p.tau_np, p.tau_np])


class Foveation(NamedTuple):
    """What kim21 derives per pixel from its eccentricity e, once per change of the frustum, gaze or parameters."""

    samples: np.ndarray  # (n,) uint8 samples per problematic subpixel in e's band (section 4.6.2); 0 beyond e_np
    tau_fov: np.ndarray  # (n,) float64 tau_fov(e) (section 4.6.1)
    alpha: np.ndarray  # (n,) float32 smoothing factor alpha(e) (section 4.7)
    table1: np.ndarray  # (n,) bool: the central pixels (e < e_np) and their 8 neighbours, whose Table 1 attributes
    # the tests read (the inspection compares a pixel with its neighbours): the presample's GBuffer.kept
    spans: np.ndarray  # (height, 2) int64: the columns [first, last + 1) of each row's central pixels; (0, 0): none

    @classmethod
    def empty(cls, height: int, width: int) -> Foveation:
        n = height * width
        spans = np.empty((height, 2), np.int64)
        return cls(np.empty(n, np.uint8), np.empty(n), np.empty(n, np.float32), np.empty(n, bool), spans)


@serial
def _bezier_y_at_x(x0, x1, x2, y0, y1, y2, e):
    """y of the quadratic Bezier at the parameter where x(t) = e; the linear case when a = 0."""
    a = x0 - 2.0 * x1 + x2
    b = 2.0 * (x1 - x0)
    c = x0 - e
    if abs(a) < 1e-12 * max(abs(b), 1e-300):
        t = -c / b if b != 0.0 else 0.0
    else:
        disc = max(b * b - 4.0 * a * c, 0.0)
        q = -0.5 * (b + math.copysign(math.sqrt(disc), b))
        t1 = q / a
        t2 = c / q if q != 0.0 else t1
        t = t1 if -1e-9 <= t1 <= 1.0 + 1e-9 else t2
    t = min(max(t, 0.0), 1.0)
    u = 1.0 - t
    return u * u * y0 + 2.0 * u * t * y1 + t * t * y2


@inline
def tau_fov(e, ctrl):
    """kim2021's tau_fov(e): y1(x1^-1(e)) on [0, e_f], y2(x2^-1(e)) on (e_f, e_np], tau_np beyond."""
    if e <= ctrl[2]:
        return _bezier_y_at_x(ctrl[0], ctrl[1], ctrl[2], ctrl[3], ctrl[4], ctrl[5], max(e, 0.0))
    if e <= ctrl[8]:
        return _bezier_y_at_x(ctrl[6], ctrl[7], ctrl[8], ctrl[9], ctrl[10], ctrl[11], e)
    return ctrl[11]


@serial
def tau_fov_array(e, ctrl):
    out = np.empty(e.shape[0])
    for i in range(e.shape[0]):
        out[i] = tau_fov(e[i], ctrl)
    return out


def alpha_knots(p: Kim21Params) -> np.ndarray:
    """The eccentricities where alpha(e) takes p.alpha: 0, e_f, e_p, e_m, e_np, e_max."""
    return np.array([0.0, p.e_f, p.e_p, p.e_m, p.e_np, p.e_max])


def alpha_of_eccentricity(ecc: np.ndarray, p: Kim21Params) -> np.ndarray:
    """alpha(e), piecewise linear through p.alpha at alpha_knots, constant beyond."""
    return np.interp(ecc, alpha_knots(p), p.alpha).astype(np.float32)


@serial
def _foveation_row(y, ecc, ctrl, bounds, counts, e_np, alpha_x, alpha_y, fov):
    samples, tau, alpha, _, spans = fov
    width = ecc.shape[1]
    central = most = 0
    first, last = width, -1
    for x in range(width):
        i = y * width + x
        e = ecc[y, x]
        band = 0
        while band < 3 and e >= bounds[band]:
            band += 1
        inside = e < e_np
        samples[i] = counts[band] if inside else 0
        central += inside
        most += samples[i]
        tau[i] = tau_fov(e, ctrl)
        alpha[i] = np.interp(e, alpha_x, alpha_y)
        if inside:
            first, last = min(first, x), x
    spans[y, 0], spans[y, 1] = (first, last + 1) if last >= 0 else (0, 0)
    return central, most


@kernel
def _foveation(ecc, ctrl, bounds, counts, e_np, alpha_x, alpha_y, fov):
    """Every pixel's Foveation from the eccentricity map ecc (h, w); returns the number of central pixels (e < e_np)
    and the extra samples of section 4.6.2 when every subpixel of each is problematic."""
    central = most = 0
    for y in nb.prange(ecc.shape[0]):
        row_central, row_most = _foveation_row(np.uint64(y), ecc, ctrl, bounds, counts, e_np, alpha_x, alpha_y, fov)
        central += row_central
        most += row_most
    for y in nb.prange(ecc.shape[0]):
        _near_central_row(np.uint64(y), ecc.shape[1], fov.samples, fov.table1)
    return central, 4 * most


@serial
def _near_central_row(y, width, samples, out):
    """Row y of Foveation.table1: whether a pixel or one of its 8 neighbours is central (samples > 0), without
    branches."""
    height = samples.shape[0] // width
    rows = (max(y - 1, 0) * width, y * width, min(y + 1, height - 1) * width)
    for x in range(width):
        left, right = max(x - 1, 0), min(x + 1, width - 1)
        near = False
        for r in rows:
            near |= (samples[r + left] > 0) | (samples[r + x] > 0) | (samples[r + right] > 0)
        out[y * width + x] = near
