"""weier16's post filter (weier2016 section 3.5): a resampled pixel outside the fovea takes the accumulated light
buffer of the closest reconstructed pixel on its surface, found by random taps in a window sized by the nearest one
along the image axes; on the image shown, not the cache."""

from __future__ import annotations

import math

import numba as nb

from hmdrt.foveation.stages.reproject import ROWS
from hmdrt.foveation.weier16.params import FOVEA, FRESH, RESAMPLE, TRACED
from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.rng import uniform
from hmdrt.kernels.schedule import claim
from hmdrt.optics.projection import FAR, world_point


@serial
def _lends(flags, info, y, x):
    """Section 3.5's reconstructed pixel, as this filter takes it: traced this frame and merged into its cache
    (its light buffer holds more than one sample)."""
    return flags[y, x] & (TRACED | FRESH) == TRACED and info[y, x, 1] > 1.0


@inline
def _donor(ty, tx, surfaces, cur, q, qx, qy, qz, rule):
    """Whether reconstructed pixel (ty, tx) lies on sample q's surface: its normal within rule.normal of q's
    and its hit point off the plane through q's (qx, qy, qz) by at most rule.plane of q's distance."""
    r, normal = surfaces.index[ty, tx], surfaces.normal
    if normal[q, 0] * normal[r, 0] + normal[q, 1] * normal[r, 1] + normal[q, 2] * normal[r, 2] < rule.normal:
        return False
    px, py, pz = world_point(cur, tx + 0.5, ty + 0.5, surfaces.depth[r])
    off = normal[q, 0] * (px - qx) + normal[q, 1] * (py - qy) + normal[q, 2] * (pz - qz)
    return abs(off) <= rule.plane * surfaces.depth[q]


@inline
def _nearest_on_axes(y, x, flags, info, surfaces, cur, q, qx, qy, qz, rule):
    """Section 3.5: how far the nearest donor (reconstructed, on q's surface) lies along the image axes from
    pixel (y, x), 0 for none within rule.radius."""
    h, w = flags.shape
    # the four neighbours spelled out, _lends inlined by hand: a loop over offsets or a call per neighbour made
    # this search 1.5 to 8 times slower at rift_s (numba's reference counting of the tuples)
    for d in range(1, rule.radius + 1):
        if x + d < w and flags[y, x + d] & (TRACED | FRESH) == TRACED and info[y, x + d, 1] > 1.0:
            if _donor(y, x + d, surfaces, cur, q, qx, qy, qz, rule):
                return d
        if x >= d and flags[y, x - d] & (TRACED | FRESH) == TRACED and info[y, x - d, 1] > 1.0:
            if _donor(y, x - d, surfaces, cur, q, qx, qy, qz, rule):
                return d
        if y + d < h and flags[y + d, x] & (TRACED | FRESH) == TRACED and info[y + d, x, 1] > 1.0:
            if _donor(y + d, x, surfaces, cur, q, qx, qy, qz, rule):
                return d
        if y >= d and flags[y - d, x] & (TRACED | FRESH) == TRACED and info[y - d, x, 1] > 1.0:
            if _donor(y - d, x, surfaces, cur, q, qx, qy, qz, rule):
                return d
    return 0


@inline
def _post_pixel(y, x, flags, surfaces, samples, final, cur, rule, image):
    """Section 3.5 at pixel (y, x): the distance to the nearest donor along the axes sizes a window sampled
    rule.taps times, and the closest donor among the taps lends its accumulated light buffer."""
    h, w = flags.shape
    q = surfaces.index[y, x]
    if surfaces.depth[q] >= FAR:
        return
    qx, qy, qz = world_point(cur, x + 0.5, y + 0.5, surfaces.depth[q])
    info = final.info
    reach = _nearest_on_axes(y, x, flags, info, surfaces, cur, q, qx, qy, qz, rule)
    if reach == 0:
        return
    best, best_d2, i = -1, 1 << 30, y * w + x
    for t in range(rule.taps):
        ox = int(math.floor((2.0 * uniform(i + rule.seed, 11, 2 * t) - 1.0) * reach + 0.5))
        oy = int(math.floor((2.0 * uniform(i + rule.seed, 11, 2 * t + 1) - 1.0) * reach + 0.5))
        ty, tx, d2 = y + oy, x + ox, ox * ox + oy * oy
        if (
            d2 < best_d2
            and 0 <= ty < h
            and 0 <= tx < w
            and _lends(flags, info, ty, tx)
            and _donor(ty, tx, surfaces, cur, q, qx, qy, qz, rule)
        ):
            best, best_d2 = ty * w + tx, d2
    if best < 0:
        return
    by, bx = best // w, best % w
    for c in range(3):
        # the sample's colour minus its own stochastic part is >= 0 exactly; max() only absorbs float rounding
        rest = max(samples.rgb[q, c] - samples.albedo[q, c] * samples.light[q, c], 0.0)
        image[y, x, c] = rest + samples.albedo[q, c] * final.light[by, bx, c]


@serial
def _post_rows(y0, y1, selection, surfaces, samples, final, cur, rule, image):
    flags = selection.flags
    for y in range(y0, y1):
        if not selection.resampled[y]:
            continue
        for x in range(flags.shape[1]):
            if flags[y, x] & (RESAMPLE | FOVEA) == RESAMPLE:
                _post_pixel(y, x, flags, surfaces, samples, final, cur, rule, image)


@kernel
def _post(selection, surfaces, samples, final, cur, rule, image, counter, threads):
    """weier2016 section 3.5 on the image shown: each resampled pixel outside the fovea takes the accumulated
    light buffer of the closest donor found (_post_pixel); the cache keeps the colour before the filter."""
    h = selection.flags.shape[0]
    blocks = (h + ROWS - 1) // ROWS
    for _ in nb.prange(threads):
        b = claim(counter)
        while b < blocks:
            _post_rows(b * ROWS, min(h, (b + 1) * ROWS), selection, surfaces, samples, final, cur, rule, image)
            b = claim(counter)
