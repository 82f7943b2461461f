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


@inline
def _rgb(color, i):
    """Row i of color (n, 3) as three values."""
    return color[i, 0], color[i, 1], color[i, 2]


@inline
def _contrast_fails(colours, tau):
    """Mitchell's contrast (max - min) / (max + min) of four colours (each as _rgb gives it), per channel, against
    tau x (1.36, 1.02, 2.04)."""
    a, b, c, d = colours
    for ch in range(3):
        va, vb, vc, vd = a[ch], b[ch], c[ch], d[ch]
        lo, hi = min(min(va, vb), min(vc, vd)), max(max(va, vb), max(vc, vd))
        if hi + lo > 0.0 and (hi - lo) / (hi + lo) > MITCHELL[ch] * tau:
            return True
    return False


@inline
def _pair_contrast_fails(a, b, tau):
    """Mitchell's contrast between two colours (_rgb)."""
    for ch in range(3):
        va, vb = a[ch], b[ch]
        lo, hi = min(va, vb), max(va, vb)
        if hi + lo > 0.0 and (hi - lo) / (hi + lo) > MITCHELL[ch] * tau:
            return True
    return False


TABLE1 = ("object_id", "normal_shading", "shadow_count", "textured")  # the G-buffer attributes _geometry reads


@inline
def _geometry(hits):
    """The attributes of Table 1's geometry tests as a plain tuple (object id, normal, shadow count, texture), which
    row functions unpack once: each array a per-pixel helper takes (alone or in a tuple) costs numba an atomic
    reference count on the way in and out where the helper branches, shared by the threads (kim21's inspection
    took twice as long). The helpers below take the attributes' values."""
    return hits.object_id, hits.normal_shading, hits.shadow_count, hits.textured


@inline
def _discordant_threshold(obj_a, obj_b, normal_dot, shadow_a, shadow_b, tex_a, tex_b, taus, normal_cos):
    """The smallest of taus (object id, normal, shadow count, texture) over the attributes on which two hits
    disagree, inf when they agree on all (Table 1). Normals (normal_dot, their dot product) disagree when both are
    hits and it is below normal_cos. A miss (object id -1) has no shadow and no texture, whatever its other
    attributes hold: a secondary half is cleared in its object ids alone (reuse._clear)."""
    hit_a, hit_b = obj_a >= 0, obj_b >= 0
    tau = math.inf
    if obj_a != obj_b:
        tau = taus[0]
    if hit_a and hit_b and normal_dot < normal_cos:
        tau = min(tau, taus[1])
    if (shadow_a if hit_a else 0) != (shadow_b if hit_b else 0):
        tau = min(tau, taus[2])
    if (tex_a and hit_a) != (tex_b and hit_b):
        tau = min(tau, taus[3])
    return tau


@inline
def _dot(ns_a, i, ns_b, j):
    """The dot product of normal i of ns_a and normal j of ns_b."""
    return ns_a[i, 0] * ns_b[j, 0] + ns_a[i, 1] * ns_b[j, 1] + ns_a[i, 2] * ns_b[j, 2]


@inline
def _taus(thresholds):
    """Table 1's geometry thresholds at the primary and at the secondary hit (thresholds[1:5], thresholds[5:9])."""
    t = thresholds
    return (t[1], t[2], t[3], t[4]), (t[5], t[6], t[7], t[8])


@serial
def _box_contrast_row(y, width, ref, tau_fov, bound, box, passes, x0, x1):
    """passes[x] for the pixels x in [x0, x1) of row y (those the inspection may read: its central ones) = whether
    Mitchell's contrast of the 3x3 box around pixel (x, y) of ref (n, 3), clamped to the image, stays within bound x
    tau_fov x (1.36, 1.02, 2.04) in every channel, with a margin over float32 rounding. A 2x2 subpixel block inside
    the box has no more contrast (it grows with max, falls with min, for non-negative colours), so it passes too.
    Separably, in loops that vectorise (unsigned indices: no negative-index wraparound; selects, no branches): each
    column's three rows into box (lowest and highest per channel, 6 rows of the row's width + 2, the edge columns
    repeated either side), for the columns the boxes read, then three columns of those."""
    height, u, one, two = ref.shape[0] // width, np.uint64, np.uint64(1), np.uint64(2)
    flat = ref.reshape(-1)
    top, mid, bottom = max(y - 1, 0) * width, y * width, min(y + 1, height - 1) * width
    c0, c1 = max(x0 - 1, 0), min(x1 + 1, width)  # the columns the boxes of [x0, x1) read
    for x in range(x0, x1):
        passes[x] = True
    for ch in range(3):
        lo, hi, scale = box[ch], box[3 + ch], MITCHELL[ch]
        t, m, b = u(3 * top + ch), u(3 * mid + ch), u(3 * bottom + ch)
        for x in range(c0, c1):
            k = u(3 * x)
            va, vb, vc = np.float64(flat[t + k]), np.float64(flat[m + k]), np.float64(flat[b + k])
            lo[u(x) + one], hi[u(x) + one] = min(min(va, vb), vc), max(max(va, vb), vc)
        lo[0], hi[0], lo[width + 1], hi[width + 1] = lo[1], hi[1], lo[width], hi[width]
        for x in range(x0, x1):
            i = u(x)
            low, high = min(min(lo[i], lo[i + one]), lo[i + two]), max(max(hi[i], hi[i + one]), hi[i + two])
            spread = np.divide(high - low, high + low) * (1.0 + 1e-6)
            fails = (low < 0.0) | ((high + low > 0.0) & (spread > scale * (bound * tau_fov[u(mid) + i])))
            passes[i] = passes[i] & (not fails)


@serial
def _inspect_row(y, width, ref, primary, secondary, fov, flags, tests, sub_mask, box, passes):
    """Row y of the two-step disparity test of every subpixel of every central pixel not reused: the 4-bit mask of
    the problematic subpixels (NW, NE, SW, SE), written for the row's central columns (fov.spans) alone, which is
    all that _subpixel_samples and _resolve read. A subpixel whose contrast passes at the smallest threshold passes
    at tau_sel too, so step one runs only where the contrast is high enough to matter, and a pixel whose 3x3
    neighbourhood passes there is done. Returns the row's extra samples and problematic subpixels."""
    height = flags.shape[0] // width
    obj, ns, shadow, tex = _geometry(primary)
    obj2, ns2, shadow2, tex2 = _geometry(secondary)
    thresholds, normal_cos = tests.thresholds, tests.normal_cos
    taus, taus2 = _taus(thresholds)
    counts, tau_fov_ = fov.samples, fov.tau_fov
    lowest = thresholds.min()
    x0, x1 = fov.spans[y, 0], fov.spans[y, 1]
    _box_contrast_row(y, width, ref, tau_fov_, lowest, box, passes, x0, x1)
    samples = subpixels = 0
    for x in range(x0, x1):
        i = np.uint64(y * width + x)  # unsigned indices: no negative-index wraparound on the loads
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
            a, b, c = np.uint64(y * width + nx), np.uint64(ny * width + x), np.uint64(ny * width + nx)
            colours = _rgb(ref, i), _rgb(ref, a), _rgb(ref, b), _rgb(ref, c)
            if not _contrast_fails(colours, lowest * tau_f):
                continue
            tau = math.inf  # step one, tau_sel: the neighbours' geometry at the primary and the secondary hit
            for j in (a, b, c):
                at_primary = _discordant_threshold(
                    obj[i], obj[j], _dot(ns, i, ns, j), shadow[i], shadow[j], tex[i], tex[j], taus, normal_cos
                )
                at_secondary = _discordant_threshold(
                    obj2[i], obj2[j], _dot(ns2, i, ns2, j), shadow2[i], shadow2[j], tex2[i], tex2[j], taus2, normal_cos
                )
                tau = min(tau, min(at_primary, at_secondary))
            tau = (thresholds[0] if tau == math.inf else tau) * tau_f
            if _contrast_fails(colours, tau):
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
            np.uint64(y), width, ref, primary, secondary, fov, flags, tests, sub_mask, box[t], passes[t]
        )
        subpixels += sub
    return subpixels
