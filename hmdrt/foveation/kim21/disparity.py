"""kim21's two-step disparity test per 2x2 subpixel (kim2021 sections 3 and 4.6.1): geometry discordance with any of
the three neighbours at the primary or secondary hit (Table 1) selects tau_sel, then Mitchell's contrast is compared
with (1.36, 1.02, 2.04) x tau_fov(e) x tau_sel; the tests' thresholds, which section 4.4's reuse test shares."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.kernels.jit import inline, kernel, serial

MITCHELL = (1.36, 1.02, 2.04)  # kim2021 section 3: the contrast threshold vector per tau


class Tests(NamedTuple):
    """The thresholds of the disparity and reusability tests (Table 1; sections 4.4 and 4.6.1)."""

    thresholds: np.ndarray  # (9,) tau_col, then object id, normal, shadow count, texture at the primary, secondary hit
    normal_cos: float
    tau_reuse: float
    n_reuse_max: int
    rel_depth: float
    reuse_px: float


@serial
def _contrast_fails(color, a, b, c, d, tau):
    """Mitchell's contrast (max - min) / (max + min) of rows a, b, c, d of color (n, 3), per channel,
    against tau x (1.36, 1.02, 2.04)."""
    for ch in range(3):
        va, vb, vc, vd = color[a, ch], color[b, ch], color[c, ch], color[d, ch]
        lo, hi = min(min(va, vb), min(vc, vd)), max(max(va, vb), max(vc, vd))
        if hi + lo > 0.0 and (hi - lo) / (hi + lo) > MITCHELL[ch] * tau:
            return True
    return False


@serial
def _pair_contrast_fails(color_a, i, color_b, j, tau):
    """Mitchell's contrast between pixel i of color_a and pixel j of color_b."""
    for ch in range(3):
        va, vb = color_a[i, ch], color_b[j, ch]
        lo, hi = min(va, vb), max(va, vb)
        if hi + lo > 0.0 and (hi - lo) / (hi + lo) > MITCHELL[ch] * tau:
            return True
    return False


@inline
def _geometry(hits):
    """The attributes of Table 1's geometry tests as a plain tuple (object id, normal, shadow count, texture): row
    functions take them out of the G-buffer once, since every namedtuple a helper receives costs a reference count
    per array."""
    return hits.object_id, hits.normal_shading, hits.shadow_count, hits.textured


@inline
def _discordant_threshold(a, i, b, j, thresholds, first, normal_cos):
    """The smallest of thresholds[first:first + 4] over the attributes (object id, normal, shadow count, texture)
    on which hit i of geometry a and hit j of geometry b disagree, inf when they agree on all (Table 1). Normals
    disagree when both are hits and their dot product is below normal_cos."""
    obj_a, ns_a, shadow_a, tex_a = a
    obj_b, ns_b, shadow_b, tex_b = b
    tau = math.inf
    if obj_a[i] != obj_b[j]:
        tau = thresholds[first]
    dot = ns_a[i, 0] * ns_b[j, 0] + ns_a[i, 1] * ns_b[j, 1] + ns_a[i, 2] * ns_b[j, 2]
    if obj_a[i] >= 0 and obj_b[j] >= 0 and dot < normal_cos:
        tau = min(tau, thresholds[first + 1])
    if shadow_a[i] != shadow_b[j]:
        tau = min(tau, thresholds[first + 2])
    if tex_a[i] != tex_b[j]:
        tau = min(tau, thresholds[first + 3])
    return tau


@inline
def _discordance(primary, secondary, i, other_primary, other_secondary, j, thresholds, normal_cos):
    """The smallest threshold over Table 1's geometry attributes on which pixel i of (primary, secondary) and
    pixel j of (other_primary, other_secondary) disagree, at the primary or the secondary hit; inf when they agree."""
    tau = _discordant_threshold(primary, i, other_primary, j, thresholds, 1, normal_cos)
    return min(tau, _discordant_threshold(secondary, i, other_secondary, j, thresholds, 5, normal_cos))


@inline
def _tau_sel(i, a, b, c, primary, secondary, thresholds, normal_cos):
    """Step one of a subpixel's disparity test: the smallest threshold over the geometry attributes on which
    pixel i disagrees with neighbour a, b or c at the primary or the secondary hit; tau_col when it agrees."""
    tau = math.inf
    for j in (a, b, c):
        tau = min(tau, _discordance(primary, secondary, i, primary, secondary, j, thresholds, normal_cos))
    return thresholds[0] if tau == math.inf else tau


@serial
def _box_contrast_row(y, width, ref, tau_fov, bound, box, passes):
    """passes[x] = whether Mitchell's contrast of the 3x3 box around pixel (x, y) of ref (n, 3), clamped to the
    image, stays within bound x tau_fov x (1.36, 1.02, 2.04) in every channel, with a margin over float32 rounding.
    A 2x2 subpixel block inside the box has no more contrast (it grows with max, falls with min, for non-negative
    colours), so it passes too. Separably, in loops that vectorise (unsigned indices: no negative-index wraparound;
    selects, no branches): each column's three rows into box (lowest and highest per channel, 6 rows of the row's
    width + 2, the edge columns repeated either side), then three columns of those."""
    height, u, one, two = ref.shape[0] // width, np.uint64, np.uint64(1), np.uint64(2)
    flat = ref.reshape(-1)
    top, mid, bottom = max(y - 1, 0) * width, y * width, min(y + 1, height - 1) * width
    for x in range(width):
        passes[x] = True
    for ch in range(3):
        lo, hi, scale = box[ch], box[3 + ch], MITCHELL[ch]
        t, m, b = u(3 * top + ch), u(3 * mid + ch), u(3 * bottom + ch)
        for x in range(width):
            k = u(3 * x)
            va, vb, vc = np.float64(flat[t + k]), np.float64(flat[m + k]), np.float64(flat[b + k])
            lo[u(x) + one], hi[u(x) + one] = min(min(va, vb), vc), max(max(va, vb), vc)
        lo[0], hi[0], lo[width + 1], hi[width + 1] = lo[1], hi[1], lo[width], hi[width]
        for x in range(width):
            i = u(x)
            low, high = min(min(lo[i], lo[i + one]), lo[i + two]), max(max(hi[i], hi[i + one]), hi[i + two])
            spread = np.divide(high - low, high + low) * (1.0 + 1e-6)
            fails = (low < 0.0) | ((high + low > 0.0) & (spread > scale * (bound * tau_fov[u(mid) + i])))
            passes[i] = passes[i] & (not fails)


@serial
def _inspect_row(y, width, ref, primary, secondary, fov, flags, tests, sub_mask, box, passes):
    """Row y of the two-step disparity test of every subpixel of every central pixel not reused: the 4-bit mask of
    the problematic subpixels (NW, NE, SW, SE). A subpixel whose contrast passes at the smallest threshold passes
    at tau_sel too, so step one runs only where the contrast is high enough to matter, and a pixel whose 3x3
    neighbourhood passes there is done. Returns the row's extra samples and problematic subpixels."""
    height = flags.shape[0] // width
    p, s2 = _geometry(primary), _geometry(secondary)
    thresholds, normal_cos = tests.thresholds, tests.normal_cos
    counts, tau_fov_ = fov.samples, fov.tau_fov
    lowest = thresholds.min()
    _box_contrast_row(y, width, ref, tau_fov_, lowest, box, passes)
    samples = subpixels = 0
    for x in range(width):
        i = y * width + x
        sub_mask[i] = 0
        k = np.int64(counts[i])
        if k == 0 or flags[i] != 0 or passes[x]:
            continue
        tau_f = tau_fov_[i]
        mask = 0
        for s in range(4):
            dx = -1 if s & 1 == 0 else 1
            dy = -1 if s < 2 else 1
            nx, ny = min(max(x + dx, 0), width - 1), min(max(y + dy, 0), height - 1)
            a, b, c = y * width + nx, ny * width + x, ny * width + nx
            if not _contrast_fails(ref, i, a, b, c, lowest * tau_f):
                continue
            tau = _tau_sel(i, a, b, c, p, s2, thresholds, normal_cos) * tau_f
            if _contrast_fails(ref, i, a, b, c, tau):
                mask |= 1 << s
                samples += k
                subpixels += 1
        sub_mask[i] = mask
    return samples, subpixels


@kernel
def _inspect(width, ref, primary, secondary, fov, flags, tests, sub_mask, row_samples, box, passes):
    """_inspect_row over the image: row_samples[y] = row y's extra samples; returns the problematic subpixels. box and
    passes: _box_contrast_row's scratch, a row per numba thread (nb.get_thread_id())."""
    subpixels = 0
    for y in nb.prange(flags.shape[0] // width):
        t = nb.get_thread_id()
        row_samples[y], sub = _inspect_row(
            y, width, ref, primary, secondary, fov, flags, tests, sub_mask, box[t], passes[t]
        )
        subpixels += sub
    return subpixels
