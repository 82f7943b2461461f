"""Spatial filters on reconstructed images.

Contrast enhancement for peripheral vision (weier2018 section 3.2, "DoF Combine", after Patney et
al. 2016): each pixel is pushed away from a blurred version of its surroundings, the blur taken from
the pyramid with a kernel that widens with eccentricity, five quincunx taps per pixel. It is faded in
across the transition region, so the fovea stays untouched. The blur's level depends only on the
eccentricity, so it is computed once per gaze (contrast_levels); the enhancement itself runs inside
the final combine pass (dof.combine), pixel by pixel.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.stages.pyramid import quincunx_mean, quincunx_offset
from hmdrt.jit import inline, kernel

DEGREES_PER_LEVEL = 5.0  # the blur's pyramid level grows by one every 5 degrees beyond r0


class Contrast(NamedTuple):
    """Contrast enhancement's settings: strength (0: off), the transition region [r0, r1) it fades in
    across, and the blur's pyramid level per pixel (contrast_levels)."""

    strength: float
    r0: float
    r1: float
    levels: np.ndarray  # (height, width, 2) float32: the blur's pyramid level and quincunx offset per pixel


@kernel
def _levels(ecc, r0, degrees_per_level, out):
    h, w = ecc.shape
    for y in nb.prange(h):
        for x in range(w):
            level = math.log2(1.0 + max(ecc[y, x] - r0, 0.0) / degrees_per_level)
            out[y, x, 0], out[y, x, 1] = level, quincunx_offset(level)


def contrast_levels(
    ecc: np.ndarray, r0: float, out: np.ndarray, degrees_per_level: float = DEGREES_PER_LEVEL
) -> np.ndarray:
    """The blur's pyramid level at every pixel, log2(1 + max(e - r0, 0) / degrees_per_level), and its quincunx
    offset, into out (height, width, 2)."""
    _levels(ecc, r0, degrees_per_level, out)
    return out


@inline
def enhance(r, g, b, e, x, y, contrast, pyramid):
    """color + strength x fade(e) x (color - blur_e(color)) at pixel (x, y) of eccentricity e, the blur from
    the pyramid around the pixel's centre. Negative results are cut at zero (light cannot be negative)."""
    strength, r0, r1, levels = contrast
    fade = 0.0 if e <= r0 else (1.0 if e >= r1 or r1 <= r0 else (e - r0) / (r1 - r0))
    if fade <= 0.0:
        return r, g, b
    br, bg, bb = quincunx_mean(pyramid, levels[y, x, 0], levels[y, x, 1], x + 0.5, y + 0.5)
    gain = strength * fade
    return max(r + gain * (r - br), 0.0), max(g + gain * (g - bg), 0.0), max(b + gain * (b - bb), 0.0)
