"""Spatial filters on reconstructed images.

Contrast enhancement for peripheral vision (weier2018 section 3.2, "DoF Combine", after Patney et
al. 2016): each pixel is pushed away from a blurred version of its surroundings whose kernel widens with
eccentricity, the blur taken from the reconstruction pyramid sampled several times. It is faded in across
the transition region, so the fovea stays untouched. The blur's level depends only on the eccentricity,
so it is computed once per gaze (contrast_levels). The several taps are taken once per texel rather than
once per pixel: every level of the pyramid is prefiltered with the five quincunx taps of weier2018
Figure 3, half a texel apart (prefilter, 1.33 texels per pixel), and each pixel then reads that filtered
pyramid trilinearly at its level, inside the final combine pass (dof.combine); ten bilinear taps per
pixel cost eight times as much for the same kernel width. The finest levels are read only near r0, where the
blur is narrow, so they are prefiltered only there (enhance_windows, once per gaze with the levels).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.stages.pyramid import Pyramid, pixel_texels, sample_row
from hmdrt.kernels.jit import inline, kernel, serial

DEGREES_PER_LEVEL = 5.0  # the blur's pyramid level grows by one every 5 degrees beyond r0


class Contrast(NamedTuple):
    """Contrast enhancement's settings: strength (0: off), the transition region [r0, r1) it fades in
    across, and the blur's pyramid level per pixel (contrast_levels)."""

    strength: float
    r0: float
    r1: float
    levels: np.ndarray  # (height, width) float32: the blur's pyramid level per pixel, -1 where e <= r0


@kernel
def _levels(ecc, r0, degrees_per_level, out):
    h, w = ecc.shape
    for y in nb.prange(h):
        for x in range(w):
            e = ecc[y, x]
            out[y, x] = math.log2(1.0 + (e - r0) / degrees_per_level) if e > r0 else -1.0


def contrast_levels(
    ecc: np.ndarray, r0: float, out: np.ndarray, degrees_per_level: float = DEGREES_PER_LEVEL
) -> np.ndarray:
    """The blur's pyramid level at every pixel, log2(1 + (e - r0) / degrees_per_level), into out (height, width);
    -1 where the enhancement does not apply (e <= r0), so that enhance_row hands a row of them to sample_row as
    it is."""
    _levels(ecc, r0, degrees_per_level, out)
    return out


@serial
def _fade(e, r0, r1):
    """How much of the enhancement applies at eccentricity e: none inside r0, all from r1. Selects, and np.divide
    without `/`'s zero-division check (r1 <= r0 takes the other side), so that a loop over pixels vectorises."""
    ramp = np.divide(e - r0, r1 - r0)
    return 0.0 if e <= r0 else (1.0 if e >= r1 or r1 <= r0 else ramp)


FINE_LEVELS = 2  # the finest levels: read only by the pixels nearest r0 (enhance_windows)


@kernel
def _prefilter_level(data, o, w, h, window, out):
    """Level texels [o, o + w h) inside `window` (x0, x1, y0, y1: texel columns [x0, x1) of rows [y0, y1)): the
    mean of the texel and the four bilinear taps half a texel away on its diagonals, each the mean of a 2x2
    block, so together a 3x3 binomial; edges repeat, as pyramid lookups do. Row views and float32 constants: no
    negative-index checks and no float64 round trips in the loop."""
    two, centre_weight, ring_weight = np.float32(2.0), np.float32(0.2), np.float32(0.05)
    x0, x1, y0, y1 = window[0], window[1], window[2], window[3]
    for y in nb.prange(y0, y1):
        up = data[o + max(y - 1, 0) * w : o + max(y - 1, 0) * w + w]
        mid = data[o + y * w : o + y * w + w]
        down = data[o + min(y + 1, h - 1) * w : o + min(y + 1, h - 1) * w + w]
        row = out[o + y * w : o + y * w + w]
        for x in range(x0, x1):
            left, right = max(x - 1, 0), min(x + 1, w - 1)
            for c in range(3):
                top = up[left, c] + two * up[x, c] + up[right, c]
                middle = mid[left, c] + two * mid[x, c] + mid[right, c]
                bottom = down[left, c] + two * down[x, c] + down[right, c]
                row[x, c] = centre_weight * mid[x, c] + ring_weight * (top + two * middle + bottom)


def prefilter(pyramid: Pyramid, out: Pyramid, windows: np.ndarray | None = None) -> Pyramid:
    """Every level of `pyramid` filtered with weier2018 Figure 3's quincunx (the texel and four diagonal taps
    half a texel away, averaged) into `out`, a pyramid of the same size: colour channels only. windows
    (levels, 4) int64, as enhance_windows gives: only those texels of each level (None: all)."""
    for k in range(len(pyramid.offsets)):
        w, h = pyramid.widths[k], pyramid.heights[k]
        window = np.array([0, w, 0, h], np.int64) if windows is None else windows[k]
        _prefilter_level(pyramid.data, pyramid.offsets[k], w, h, window, out.data)
    return out


@kernel
def _read_spans(ecc, contrast, spans):
    """Per row, the first and last pixel that enhance_row reads below level m + 1, for m < FINE_LEVELS (first
    past last when none)."""
    _, r0, r1, levels = contrast
    h, w = ecc.shape
    for y in nb.prange(h):
        for m in range(FINE_LEVELS):
            spans[y, m, 0], spans[y, m, 1] = w, -1
        for x in range(w):
            if _fade(ecc[y, x], r0, r1) > 0.0:
                for m in range(FINE_LEVELS):
                    if levels[y, x] < m + 1:
                        spans[y, m, 0], spans[y, m, 1] = min(spans[y, m, 0], x), max(spans[y, m, 1], x)


@serial
def _windows(spans, pyramid, out):
    """enhance_windows from the rows' spans (_read_spans)."""
    widths, heights, scale_x, scale_y = pyramid.widths, pyramid.heights, pyramid.scale_x, pyramid.scale_y
    for k in range(len(widths)):
        out[k, 0], out[k, 1], out[k, 2], out[k, 3] = 0, widths[k], 0, heights[k]
    for m in range(min(FINE_LEVELS, len(widths))):
        px0, px1, py0, py1 = 1 << 62, -1, -1, -1  # the pixels' bounding box
        for y in range(spans.shape[0]):
            if spans[y, m, 1] >= spans[y, m, 0]:
                px0, px1 = min(px0, spans[y, m, 0]), max(px1, spans[y, m, 1])
                py0 = y if py0 < 0 else py0
                py1 = y
        if px1 < 0:  # no pixel reads the level
            out[m, 0] = out[m, 1] = out[m, 2] = out[m, 3] = 0
            continue
        out[m, 0], out[m, 1] = pixel_texels(px0, px1, scale_x[m], widths[m])
        out[m, 2], out[m, 3] = pixel_texels(py0, py1, scale_y[m], heights[m])


def enhance_windows(ecc: np.ndarray, contrast: Contrast, pyramid: Pyramid, spans: np.ndarray) -> np.ndarray:
    """(levels, 4) int64: the texels (x0, x1, y0, y1: columns [x0, x1) of rows [y0, y1)) of each level of a
    pyramid of `pyramid`'s size that enhance_row reads for this eccentricity map and these levels: on the
    FINE_LEVELS finest, those around the pixels near r0 that read them (the blur is narrow there); every
    coarser level whole. It depends on the gaze only, as the levels do. spans: (height, FINE_LEVELS, 2) int64
    scratch."""
    _read_spans(ecc, contrast, spans)
    out = np.empty((len(pyramid.offsets), 4), np.int64)
    _windows(spans, pyramid, out)
    return out


@inline
def enhance_row(ecc, contrast, blurred, axes, values, texels, runs, color, stride, y, rgb):
    """Row y into rgb (flat, 3 floats a pixel): color + strength x fade(e) x (color - blur_e(color)) at each pixel of
    eccentricity e, the colour read from `color` (row y's, flat, `stride` floats a pixel: rgb itself, in place, or a
    pyramid level's, copied as it is enhanced), the blur read trilinearly from the prefiltered pyramid `blurred`
    (prefilter; `axes` its pixel_axes) at the pixel's centre, for the row at once (pyramid.sample_row at the
    contrast's own row of levels, with `values`, `texels` and `runs` its scratch). Negative results are cut at zero
    (light cannot be negative). Selects, not branches, over rows flattened: inlined where it is called, with a
    constant stride, the loop vectorises (a pixel inside r0, whose blur was not sampled, keeps its colour)."""
    strength, r0, r1, blur_levels = contrast
    sample_row(blurred.data, blurred.widths, axes, y, blur_levels[y], values, texels, runs)
    blur, e = values.reshape(-1), ecc[y]
    for x in range(e.shape[0]):
        fade = _fade(e[x], r0, r1)
        gain = strength * fade
        i, j = 3 * x, stride * x
        r, g, b = color[j], color[j + 1], color[j + 2]
        er = max(r + gain * (r - blur[i]), 0.0)
        eg = max(g + gain * (g - blur[i + 1]), 0.0)
        eb = max(b + gain * (b - blur[i + 2]), 0.0)
        rgb[i], rgb[i + 1], rgb[i + 2] = (er, eg, eb) if fade > 0.0 else (r, g, b)
