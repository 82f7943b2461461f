"""Spatial filters on reconstructed images.

Contrast enhancement for peripheral vision (weier2018 section 3.2, "DoF Combine", after Patney et
al. 2016): each pixel is pushed away from a blurred version of its surroundings, the blur taken from
the pyramid with a kernel that widens with eccentricity, five quincunx taps per pixel. It is faded in
across the transition region, so the fovea stays untouched.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from hmdrt.foveation.stages.pyramid import Pyramid, quincunx_rgbd


@nb.njit(parallel=True, cache=True, nogil=True)
def _enhance(color, ecc, r0, r1, strength, degrees_per_level, pyramid, out):
    data, offsets, widths, heights = pyramid
    h, w = ecc.shape
    for y in nb.prange(h):
        for x in range(w):
            e = ecc[y, x]
            fade = 0.0 if e <= r0 else (1.0 if e >= r1 or r1 <= r0 else (e - r0) / (r1 - r0))
            if fade <= 0.0:
                for c in range(3):
                    out[y, x, c] = color[y, x, c]
                continue
            level = math.log2(1.0 + max(e - r0, 0.0) / degrees_per_level)
            br = bg = bb = 0.0
            for k in range(5):
                r, g, b, _ = quincunx_rgbd(data, offsets, widths, heights, level, x + 0.5, y + 0.5, k)
                br, bg, bb = br + 0.2 * r, bg + 0.2 * g, bb + 0.2 * b
            gain = strength * fade
            out[y, x, 0] = max(color[y, x, 0] + gain * (color[y, x, 0] - br), 0.0)
            out[y, x, 1] = max(color[y, x, 1] + gain * (color[y, x, 1] - bg), 0.0)
            out[y, x, 2] = max(color[y, x, 2] + gain * (color[y, x, 2] - bb), 0.0)


def contrast_enhance(
    color: np.ndarray,
    ecc: np.ndarray,
    pyramid: Pyramid,
    strength: float,
    r0: float,
    r1: float,
    degrees_per_level: float = 5.0,
) -> np.ndarray:
    """color + strength x fade(e) x (color - blur_e(color)); the blur's pyramid level grows by one every
    degrees_per_level beyond r0. Negative results are cut at zero (light cannot be negative)."""
    out = np.empty_like(color)
    _enhance(color, ecc, r0, r1, strength, degrees_per_level, tuple(pyramid), out)
    return out
