"""Image pyramids with pull-push reconstruction and quincunx lookups (weier2018 section 3.1).

A pyramid holds colour, weight and depth per level in one buffer. Pull-push interpolation (Marroquim
et al. 2007) turns sparse samples into a dense image: pull averages the valid children of every
texel level by level (weight min(1, sum of child weights)), push fills each texel's missing weight
from the bilinearly upsampled coarser level. The pushed pyramid is also the previous frame's colour
and depth for the next frame's reprojection and the peripheral blur of the depth of field.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

CHANNELS = 5  # r, g, b, weight, depth


class Pyramid(NamedTuple):
    data: np.ndarray  # (texels, 5) float32: r, g, b, weight, depth
    offsets: np.ndarray  # (levels,) int64 first texel of each level
    widths: np.ndarray  # (levels,) int64
    heights: np.ndarray  # (levels,) int64

    @classmethod
    def empty(cls, width: int, height: int) -> Pyramid:
        widths, heights = [width], [height]
        while widths[-1] > 1 or heights[-1] > 1:
            widths.append(max(1, (widths[-1] + 1) // 2))
            heights.append(max(1, (heights[-1] + 1) // 2))
        sizes = np.array(widths, np.int64) * np.array(heights, np.int64)
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        return cls(
            np.zeros((int(sizes.sum()), CHANNELS), np.float32),
            offsets,
            np.array(widths, np.int64),
            np.array(heights, np.int64),
        )

    def level(self, k: int) -> np.ndarray:
        """Level k as a (height, width, 5) view."""
        o = self.offsets[k]
        return self.data[o : o + self.widths[k] * self.heights[k]].reshape(self.heights[k], self.widths[k], CHANNELS)


@nb.njit(parallel=True, cache=True, nogil=True)
def _pull_level(data, o_fine, wf, hf, o_coarse, wc, hc):
    for y in nb.prange(hc):
        for x in range(wc):
            wsum = r = g = b = d = 0.0
            for dy in range(2):
                for dx in range(2):
                    fy, fx = 2 * y + dy, 2 * x + dx
                    if fy < hf and fx < wf:
                        i = o_fine + fy * wf + fx
                        w = data[i, 3]
                        if w > 0.0:
                            wsum += w
                            r, g, b, d = r + w * data[i, 0], g + w * data[i, 1], b + w * data[i, 2], d + w * data[i, 4]
            j = o_coarse + y * wc + x
            if wsum > 0.0:
                data[j, 0], data[j, 1], data[j, 2], data[j, 4] = r / wsum, g / wsum, b / wsum, d / wsum
            data[j, 3] = min(1.0, wsum)


@nb.njit(cache=True, nogil=True, inline="always")
def level_bilinear(data, o, w, h, x, y, c):
    """Channel c of a level at continuous texel coordinates (x, y), clamped at the border."""
    fx, fy = x - 0.5, y - 0.5
    x0, y0 = math.floor(fx), math.floor(fy)
    ax, ay = fx - x0, fy - y0
    ix0, iy0 = min(max(int(x0), 0), w - 1), min(max(int(y0), 0), h - 1)
    ix1, iy1 = min(max(int(x0) + 1, 0), w - 1), min(max(int(y0) + 1, 0), h - 1)
    top = data[o + iy0 * w + ix0, c] * (1.0 - ax) + data[o + iy0 * w + ix1, c] * ax
    bottom = data[o + iy1 * w + ix0, c] * (1.0 - ax) + data[o + iy1 * w + ix1, c] * ax
    return top * (1.0 - ay) + bottom * ay


@nb.njit(parallel=True, cache=True, nogil=True)
def _push_level(data, o_fine, wf, hf, o_coarse, wc, hc):
    for y in nb.prange(hf):
        for x in range(wf):
            i = o_fine + y * wf + x
            w = data[i, 3]
            if w >= 1.0:
                continue
            cx, cy = (x + 0.5) * wc / wf, (y + 0.5) * hc / hf
            for c in (0, 1, 2, 4):
                up = level_bilinear(data, o_coarse, wc, hc, cx, cy, c)
                data[i, c] = w * data[i, c] + (1.0 - w) * up if w > 0.0 else up
            data[i, 3] = 1.0


def pull_push(pyramid: Pyramid) -> None:
    """Fill every texel of level 0 from its valid samples (weight > 0), in place, coarse levels too."""
    d, o, w, h = pyramid.data, pyramid.offsets, pyramid.widths, pyramid.heights
    for k in range(1, len(o)):
        _pull_level(d, o[k - 1], w[k - 1], h[k - 1], o[k], w[k], h[k])
    for k in range(len(o) - 2, -1, -1):
        _push_level(d, o[k], w[k], h[k], o[k + 1], w[k + 1], h[k + 1])


@nb.njit(cache=True, nogil=True, inline="always")
def _level_rgbd(data, o, w, h, x, y):
    """Colour and depth of a level at continuous texel coordinates (x, y), bilinear, clamped."""
    fx, fy = x - 0.5, y - 0.5
    x0, y0 = math.floor(fx), math.floor(fy)
    ax, ay = fx - x0, fy - y0
    ix0, iy0 = min(max(int(x0), 0), w - 1), min(max(int(y0), 0), h - 1)
    ix1, iy1 = min(max(int(x0) + 1, 0), w - 1), min(max(int(y0) + 1, 0), h - 1)
    i00, i01, i10, i11 = o + iy0 * w + ix0, o + iy0 * w + ix1, o + iy1 * w + ix0, o + iy1 * w + ix1
    w00, w01, w10, w11 = (1.0 - ax) * (1.0 - ay), ax * (1.0 - ay), (1.0 - ax) * ay, ax * ay
    return (
        w00 * data[i00, 0] + w01 * data[i01, 0] + w10 * data[i10, 0] + w11 * data[i11, 0],
        w00 * data[i00, 1] + w01 * data[i01, 1] + w10 * data[i10, 1] + w11 * data[i11, 1],
        w00 * data[i00, 2] + w01 * data[i01, 2] + w10 * data[i10, 2] + w11 * data[i11, 2],
        w00 * data[i00, 4] + w01 * data[i01, 4] + w10 * data[i10, 4] + w11 * data[i11, 4],
    )


@nb.njit(cache=True, nogil=True, inline="always")
def sample_rgbd(data, offsets, widths, heights, level, x, y):
    """Colour and depth at full-resolution pixel coordinates (x, y) on a (fractional) level, trilinearly."""
    top = len(offsets) - 1
    level = min(max(level, 0.0), float(top))
    l0 = int(math.floor(level))
    r, g, b, d = _level_rgbd(
        data, offsets[l0], widths[l0], heights[l0], x * widths[l0] / widths[0], y * heights[l0] / heights[0]
    )
    t = level - l0
    if t == 0.0 or l0 == top:
        return r, g, b, d
    l1 = l0 + 1
    r1, g1, b1, d1 = _level_rgbd(
        data, offsets[l1], widths[l1], heights[l1], x * widths[l1] / widths[0], y * heights[l1] / heights[0]
    )
    return r + t * (r1 - r), g + t * (g1 - g), b + t * (b1 - b), d + t * (d1 - d)


# weier2018 Figure 3: a quincunx of five taps, the centre and the four diagonal half-texel offsets
QUINCUNX = ((0.0, 0.0), (-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5))


@nb.njit(cache=True, nogil=True, inline="always")
def quincunx_rgbd(data, offsets, widths, heights, level, x, y, k):
    """Colour and depth of the k-th quincunx tap around full-resolution (x, y) on `level` (offsets in
    that level's texels)."""
    scale = 2.0 ** max(level, 0.0)
    return sample_rgbd(data, offsets, widths, heights, level, x + QUINCUNX[k][0] * scale, y + QUINCUNX[k][1] * scale)
