"""Gaze-contingent depth of field (weier2018 section 3.2).

Circles of confusion from the tracking-aware thin-lens model, equation (3): the eye's image distance
d_i = 22.4 mm is fixed, the focus distance d_o is widened to d_n = d_o - t and d_f = d_o + t by the
mean depth-estimation inaccuracy t = 0.2 m, and the CoC is zero in [d_n, d_f], signed outside it
(positive near, negative far). Pupil diameter k and retinal resolution E set the strength. The
layered blur keeps near, focused and far fields apart: the far field takes a variable Gaussian that
ignores nearer pixels in central vision and the reconstruction pyramid in the periphery, blended
across the transition; the near field spreads over its neighbours with a coverage for alpha blending.

The paper names the presets but gives no numbers for them; the (k, E) below give CoC radii of about
2, 5 and 10 pixels for a point at 6 m while fixating 0.75 m at rift_s resolution (E is scaled to the
display's pixel density, so the blur spans the same visual angle on every profile). Equation (3) is
used as printed, with lengths in millimetres.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.stages.pyramid import Pyramid, sample_rgbd

IMAGE_DISTANCE_MM = 22.4  # d_i, the eye's lens-to-retina distance (Gross 2005)
DEPTH_INACCURACY_M = 0.2  # t, the mean gaze-depth estimation error over 6 m (Weier et al. 2018)
REFERENCE_PPD = 14.2  # rift_s pixels per degree at the centre, the density the presets were set at
MAX_BLUR_PX = 24  # radius cap of the central Gaussian and of the near-field spread


class DofPreset(NamedTuple):
    pupil_mm: float  # k
    retina: float  # E, pixels per mm^2 at REFERENCE_PPD


DOF_PRESETS: dict[str, DofPreset | None] = {
    "none": None,
    "weak": DofPreset(3.0, 0.07),
    "medium": DofPreset(4.0, 0.13),
    "strong": DofPreset(6.0, 0.17),
}


def focal_lengths(d_o_m: float, t_m: float = DEPTH_INACCURACY_M) -> tuple[float, float, float, float]:
    """(d_n, d_f, f_n, f_f) in mm: the widened focus range and the focal lengths that image each onto
    the retina (1/f = 1/d + 1/d_i). d_n is kept at 2 d_i or more (where d_o <= t would make it zero or
    negative), above the focal length so the lens equation holds, and d_f at d_n or more. d_o = inf gives
    d_n = d_f = inf and f_n = f_f = d_i: focused at infinity."""
    d_o = d_o_m * 1000.0
    d_n = max(d_o - t_m * 1000.0, 2.0 * IMAGE_DISTANCE_MM)
    d_f = max(d_o + t_m * 1000.0, d_n)
    f = lambda d: 1.0 / (1.0 / d + 1.0 / IMAGE_DISTANCE_MM)  # noqa: E731
    return d_n, d_f, f(d_n), f(d_f)


@nb.njit(cache=True, nogil=True, inline="always")
def _image_distance(f, g):
    """V(F, G) = F G / (G - F): where a lens of focal length F images an object at G (G > F); F at G = inf."""
    if math.isinf(g):
        return f
    return f * g / (g - f)


@nb.njit(cache=True, nogil=True, inline="always")
def circle_of_confusion(g_mm, d_n, d_f, f_n, f_f, k, e):
    """Equation (3): signed CoC of an object at distance g (mm); 0 inside [d_n, d_f], > 0 near, < 0 far.

    An object at or inside the focal length (g <= f: nothing closer than about 2 cm to the eye) has no real
    image; it takes the CoC of g = f (1 + 1e-9), finite and larger than any other. The blur filters cap every
    CoC at MAX_BLUR_PX (weier18 counts those pixels in its coc_capped_pixels metric)."""
    if g_mm < d_n:
        f, d = f_n, d_n
    elif g_mm > d_f:
        f, d = f_f, d_f
    else:
        return 0.0
    vg = _image_distance(f, max(g_mm, f * (1.0 + 1e-9)))  # an object at infinity is imaged at the focal plane
    return (vg - _image_distance(f, d)) * (k * vg) * e


@nb.njit(parallel=True, cache=True, nogil=True)
def _coc_map(depth_m, d_n, d_f, f_n, f_f, k, e, out):
    h, w = depth_m.shape
    for y in nb.prange(h):
        for x in range(w):
            out[y, x] = circle_of_confusion(depth_m[y, x] * 1000.0, d_n, d_f, f_n, f_f, k, e)


def coc_map(
    depth_m: np.ndarray, focus_m: float, preset: DofPreset, ppd: float, t_m: float = DEPTH_INACCURACY_M
) -> np.ndarray:
    """Per-pixel signed CoC in pixels for hit distances depth_m (m, inf for misses), focus widened by t_m."""
    d_n, d_f, f_n, f_f = focal_lengths(focus_m, t_m)
    out = np.empty(depth_m.shape, np.float32)
    _coc_map(depth_m.astype(np.float64), d_n, d_f, f_n, f_f, preset.pupil_mm, preset.retina * ppd / REFERENCE_PPD, out)
    return out


def gaze_depth(
    depth_m: np.ndarray, por: np.ndarray, ppd: float, vergence_m: float | None, radius_deg: float = 1.0
) -> float:
    """The focused depth: depth samples at and around the point of regard (weier2018 Figure 4, a centre
    and eight points on a ring), the one nearest the vergence depth when the two eyes' gaze gives one,
    else their median. (The paper feeds these measures to a per-user trained SVM; this is its stand-in.)"""
    h, w = depth_m.shape
    angles = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
    r = radius_deg * ppd
    xs = np.concatenate([[por[0]], por[0] + r * np.cos(angles)])
    ys = np.concatenate([[por[1]], por[1] + r * np.sin(angles)])
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    samples = depth_m[ys[inside].astype(int), xs[inside].astype(int)]
    samples = samples[np.isfinite(samples)]
    if len(samples) == 0:
        return vergence_m if vergence_m is not None else 1e3
    if vergence_m is not None and math.isfinite(vergence_m):
        return float(samples[np.argmin(np.abs(samples - vergence_m))])
    return float(np.median(samples))


@nb.njit(parallel=True, cache=True, nogil=True)
def _far_gauss(src, coc, central, horizontal, out):
    """One pass of the separable far-field Gaussian (sigma = |CoC| / 2) in central vision, taking only
    far-field neighbours: the focused and near fields do not bleed into the blurred background."""
    h, w = coc.shape
    for row in nb.prange(h):
        y = np.int64(row)  # prange's index is unsigned; y + d must stay a signed integer
        for x in range(w):
            c0 = coc[y, x]
            if not central[y, x] or c0 >= 0.0:
                for ch in range(3):
                    out[y, x, ch] = src[y, x, ch]
                continue
            sigma = max(-0.5 * c0, 0.5)
            # capped before the integer conversion, which would overflow for CoCs beyond about 1e18 pixels
            radius = MAX_BLUR_PX if sigma >= 0.5 * MAX_BLUR_PX else int(math.ceil(2.0 * sigma))
            wsum = r = g = b = 0.0
            for d in range(-radius, radius + 1):
                yy, xx = (y, x + d) if horizontal else (y + d, x)
                if xx < 0 or xx >= w or yy < 0 or yy >= h or coc[yy, xx] >= 0.0:
                    continue
                wt = math.exp(-0.5 * d * d / (sigma * sigma))
                wsum += wt
                r, g, b = r + wt * src[yy, xx, 0], g + wt * src[yy, xx, 1], b + wt * src[yy, xx, 2]
            out[y, x, 0], out[y, x, 1], out[y, x, 2] = r / wsum, g / wsum, b / wsum


@nb.njit(parallel=True, cache=True, nogil=True)
def _near_h(color, coc, radius, out):
    """Horizontal near-field pass: each pixel averages the near-field pixels (CoC > 0) of its row whose
    blur disc reaches it, and records the largest such reach (0 when none does)."""
    h, w = coc.shape
    for y in nb.prange(h):
        for x in range(w):
            n = reach = r = g = b = 0.0
            for xx in range(max(0, x - radius), min(w, x + radius + 1)):
                c = coc[y, xx]
                if c > 0.0 and abs(xx - x) <= c:
                    n += 1.0
                    reach = max(reach, min(c, MAX_BLUR_PX))
                    r, g, b = r + color[y, xx, 0], g + color[y, xx, 1], b + color[y, xx, 2]
            if n > 0.0:
                out[y, x, 0], out[y, x, 1], out[y, x, 2] = r / n, g / n, b / n
            out[y, x, 3] = reach


@nb.njit(parallel=True, cache=True, nogil=True)
def _near_v(hpass, radius, out):
    """Vertical near-field pass: the average over the rows whose reach covers this pixel, and the
    coverage: those rows over the disc's full diameter (1 inside a near object, falling off at its edge)."""
    h, w = hpass.shape[0], hpass.shape[1]
    for y in nb.prange(h):
        for x in range(w):
            n = reach = r = g = b = 0.0
            for yy in range(max(0, y - radius), min(h, y + radius + 1)):
                c = hpass[yy, x, 3]
                if c > 0.0 and abs(yy - y) <= c:
                    n += 1.0
                    reach = max(reach, c)
                    r, g, b = r + hpass[yy, x, 0], g + hpass[yy, x, 1], b + hpass[yy, x, 2]
            if n > 0.0:
                out[y, x, 0], out[y, x, 1], out[y, x, 2] = r / n, g / n, b / n
                out[y, x, 3] = min(1.0, n / (2.0 * reach + 1.0))
            else:
                out[y, x, 0] = out[y, x, 1] = out[y, x, 2] = out[y, x, 3] = 0.0


@nb.njit(parallel=True, cache=True, nogil=True)
def _combine(color, coc, far_central, ecc, r0, r1, pyramid, near, ramp, out):
    """Far field: the central Gaussian, the pyramid blur in the periphery, blended across [r0, r1); the
    sharp image is interpolated towards it by |CoC|; the near field is alpha-blended over."""
    data, offsets, widths, heights = pyramid
    h, w = coc.shape
    for y in nb.prange(h):
        for x in range(w):
            c = coc[y, x]
            r, g, b = color[y, x, 0], color[y, x, 1], color[y, x, 2]
            if c < 0.0:
                e = ecc[y, x]
                blend = 0.0 if e < r0 else (1.0 if e >= r1 or r1 <= r0 else (e - r0) / (r1 - r0))
                fr, fg, fb = far_central[y, x, 0], far_central[y, x, 1], far_central[y, x, 2]
                if blend > 0.0:
                    level = math.log2(max(-c, 1.0))
                    pr, pg, pb, _ = sample_rgbd(data, offsets, widths, heights, level, x + 0.5, y + 0.5)
                    fr, fg, fb = fr + blend * (pr - fr), fg + blend * (pg - fg), fb + blend * (pb - fb)
                t = min(1.0, -c / ramp)
                r, g, b = r + t * (fr - r), g + t * (fg - g), b + t * (fb - b)
            a = near[y, x, 3]
            if a > 0.0:
                r, g, b = r + a * (near[y, x, 0] - r), g + a * (near[y, x, 1] - g), b + a * (near[y, x, 2] - b)
            out[y, x, 0], out[y, x, 1], out[y, x, 2] = r, g, b


def layered_blur(
    color: np.ndarray, coc: np.ndarray, ecc: np.ndarray, r0: float, r1: float, pyramid: Pyramid, ramp: float = 2.0
) -> np.ndarray:
    """The depth-of-field image: layered near / focused / far blur with the CoC map (pixels, signed)."""
    h, w = coc.shape
    central = ecc < r1
    hpass = np.empty_like(color)
    far = np.empty_like(color)
    _far_gauss(color, coc, central, True, hpass)
    _far_gauss(hpass, coc, central, False, far)
    near_h = np.zeros((h, w, 4), np.float32)
    near = np.empty((h, w, 4), np.float32)
    radius = min(MAX_BLUR_PX, int(math.ceil(max(float(coc.max()), 0.0))))
    _near_h(color, coc, radius, near_h)
    _near_v(near_h, radius, near)
    out = np.empty_like(color)
    _combine(color, coc, far, ecc, r0, r1, tuple(pyramid), near, ramp, out)
    return out
