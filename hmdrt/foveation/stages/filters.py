"""Spatial filters on reconstructed images.

Contrast enhancement for peripheral vision (weier2018 section 3.2, "DoF Combine", after Patney et
al. 2016): each pixel is pushed away from a blurred version of its surroundings whose kernel widens with
eccentricity, the blur taken from the reconstruction pyramid sampled several times. It is faded in across
the transition region, so the fovea stays untouched. The blur's level depends only on the eccentricity,
so it is computed once per gaze (contrast_levels). The several taps are taken once per texel rather than
once per pixel: every level of the pyramid is prefiltered with the five quincunx taps of weier2018
Figure 3, half a texel apart (prefilter, 1.33 texels per pixel), and each pixel then reads that filtered
pyramid trilinearly at its level, inside the final combine pass (dof.combine); ten bilinear taps per
pixel cost eight times as much for the same kernel width.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.stages.pyramid import Pyramid, sample_row
from hmdrt.jit import kernel, serial

DEGREES_PER_LEVEL = 5.0  # the blur's pyramid level grows by one every 5 degrees beyond r0


class Contrast(NamedTuple):
    """Contrast enhancement's settings: strength (0: off), the transition region [r0, r1) it fades in
    across, and the blur's pyramid level per pixel (contrast_levels)."""

    strength: float
    r0: float
    r1: float
    levels: np.ndarray  # (height, width) float32: the blur's pyramid level per pixel


@kernel
def _levels(ecc, r0, degrees_per_level, out):
    h, w = ecc.shape
    for y in nb.prange(h):
        for x in range(w):
            out[y, x] = math.log2(1.0 + max(ecc[y, x] - r0, 0.0) / degrees_per_level)


def contrast_levels(
    ecc: np.ndarray, r0: float, out: np.ndarray, degrees_per_level: float = DEGREES_PER_LEVEL
) -> np.ndarray:
    """The blur's pyramid level at every pixel, log2(1 + max(e - r0, 0) / degrees_per_level), into out
    (height, width)."""
    _levels(ecc, r0, degrees_per_level, out)
    return out


@kernel
def _prefilter_level(data, o, w, h, out):
    """Level texels [o, o + w h): the mean of the texel and the four bilinear taps half a texel away on its
    diagonals, each the mean of a 2x2 block, so together a 3x3 binomial; edges repeat, as pyramid lookups do.
    Row views and float32 constants: no negative-index checks and no float64 round trips in the loop."""
    two, centre_weight, ring_weight = np.float32(2.0), np.float32(0.2), np.float32(0.05)
    for y in nb.prange(h):
        up = data[o + max(y - 1, 0) * w : o + max(y - 1, 0) * w + w]
        mid = data[o + y * w : o + y * w + w]
        down = data[o + min(y + 1, h - 1) * w : o + min(y + 1, h - 1) * w + w]
        row = out[o + y * w : o + y * w + w]
        for x in range(w):
            left, right = max(x - 1, 0), min(x + 1, w - 1)
            for c in range(3):
                top = up[left, c] + two * up[x, c] + up[right, c]
                middle = mid[left, c] + two * mid[x, c] + mid[right, c]
                bottom = down[left, c] + two * down[x, c] + down[right, c]
                row[x, c] = centre_weight * mid[x, c] + ring_weight * (top + two * middle + bottom)


def prefilter(pyramid: Pyramid, out: Pyramid) -> Pyramid:
    """Every level of `pyramid` filtered with weier2018 Figure 3's quincunx (the texel and four diagonal taps
    half a texel away, averaged) into `out`, a pyramid of the same size: colour channels only."""
    for k in range(len(pyramid.offsets)):
        _prefilter_level(pyramid.data, pyramid.offsets[k], pyramid.widths[k], pyramid.heights[k], out.data)
    return out


@serial
def _fade(e, r0, r1):
    """How much of the enhancement applies at eccentricity e: none inside r0, all from r1."""
    return 0.0 if e <= r0 else (1.0 if e >= r1 or r1 <= r0 else (e - r0) / (r1 - r0))


@serial
def enhance_row(ecc, contrast, blurred, axes, levels, values, y, out):
    """Row y of out enhanced in place: color + strength x fade(e) x (color - blur_e(color)) at each pixel of
    eccentricity e, the blur read trilinearly from the prefiltered pyramid `blurred` (prefilter; `axes` its
    pixel_axes) at the pixel's centre, for the row at once (pyramid.sample_row, with `levels` and `values` its
    scratch). Negative results are cut at zero (light cannot be negative)."""
    strength, r0, r1, blur_levels = contrast
    for x in range(out.shape[1]):
        levels[x] = blur_levels[y, x] if _fade(ecc[y, x], r0, r1) > 0.0 else -1.0
    sample_row(blurred.data, len(blurred.offsets) - 1, axes, y, levels, values)
    for x in range(out.shape[1]):
        fade = _fade(ecc[y, x], r0, r1)
        if fade <= 0.0:
            continue
        br, bg, bb = values[x, 0], values[x, 1], values[x, 2]
        gain = strength * fade
        r, g, b = out[y, x, 0], out[y, x, 1], out[y, x, 2]
        out[y, x, 0] = max(r + gain * (r - br), 0.0)
        out[y, x, 1] = max(g + gain * (g - bg), 0.0)
        out[y, x, 2] = max(b + gain * (b - bb), 0.0)
