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

from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.simd import (
    TEXEL_FLOATS,
    rgb_blend,
    rgb_lerp_to_blend,
    texel_blend,
    texel_blend_into,
    texel_mean,
    texel_trilinear,
)

CHANNELS = TEXEL_FLOATS  # r, g, b, depth, weight: the texel the simd intrinsics read
DEPTH, WEIGHT = 3, 4  # a texel's hit distance and weight: its colour and depth are its first 16 bytes (texel_blend)


class PixelAxes(NamedTuple):
    """Per level, the two texels either side of every full-resolution pixel centre along x and along y and the
    second one's weight (_axis): what sample_row would otherwise compute per pixel, four times. They depend
    on the pyramid's size only (pixel_axes). Along y each texel row is given as the flat index of its first texel."""

    col0: np.ndarray  # (levels, width) uint32
    col1: np.ndarray  # (levels, width) uint32
    col_weight: np.ndarray  # (levels, width) float32
    row0: np.ndarray  # (levels, height) uint64
    row1: np.ndarray  # (levels, height) uint64
    row_weight: np.ndarray  # (levels, height) float32


def _axis_table(n_pixels: int, scales: np.ndarray, sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """_axis of every pixel centre (k + 0.5) x scale on every level, in the same float64 steps."""
    g = (np.arange(n_pixels) + 0.5)[None, :] * scales[:, None] - 0.5
    k = np.floor(g)
    last = (sizes - 1)[:, None]
    i = k.astype(np.int64)
    return np.clip(i, 0, last), np.clip(i + 1, 0, last), (g - k).astype(np.float32)


class Pyramid(NamedTuple):
    data: np.ndarray  # (texels, 5) float32: r, g, b, depth, weight
    offsets: np.ndarray  # (levels,) int64 first texel of each level
    widths: np.ndarray  # (levels,) int64
    heights: np.ndarray  # (levels,) int64
    scale_x: np.ndarray  # (levels,) float64 widths[k] / widths[0]: full-resolution x to level-k texels
    scale_y: np.ndarray  # (levels,) float64 heights[k] / heights[0]

    @classmethod
    def empty(cls, width: int, height: int) -> Pyramid:
        widths, heights = [width], [height]
        while widths[-1] > 1 or heights[-1] > 1:
            widths.append(max(1, (widths[-1] + 1) // 2))
            heights.append(max(1, (heights[-1] + 1) // 2))
        w, h = np.array(widths, np.int64), np.array(heights, np.int64)
        sizes = w * h
        offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        return cls(np.zeros((int(sizes.sum()), CHANNELS), np.float32), offsets, w, h, w / width, h / height)

    def level(self, k: int) -> np.ndarray:
        """Level k as a (height, width, 5) view."""
        o = self.offsets[k]
        return self.data[o : o + self.widths[k] * self.heights[k]].reshape(self.heights[k], self.widths[k], CHANNELS)


def pixel_axes(pyramid: Pyramid) -> PixelAxes:
    """The PixelAxes of every pyramid of this one's size (a kernel argument of its own: numba's parallel kernels
    take no tuple of arrays nested in another)."""
    width, height = int(pyramid.widths[0]), int(pyramid.heights[0])
    col0, col1, col_weight = _axis_table(width, pyramid.scale_x, pyramid.widths)
    row0, row1, row_weight = _axis_table(height, pyramid.scale_y, pyramid.heights)
    first, texels = pyramid.offsets[:, None], pyramid.widths[:, None]
    return PixelAxes(
        col0.astype(np.uint32),
        col1.astype(np.uint32),
        col_weight,
        (first + row0 * texels).astype(np.uint64),
        (first + row1 * texels).astype(np.uint64),
        row_weight,
    )


@serial
def _weight(data, i, mask):
    """A texel's weight: its weight channel, or 1 / 0 from mask (level 0 only) when one is given."""
    if mask is None:
        return data[i, WEIGHT]
    return 1.0 if mask[i] else 0.0


@serial
def _axis(f, n):
    """The two texels either side of continuous texel coordinate f (centres at k + 0.5), clamped to [0, n),
    as unsigned indices (numba adds no negative-index wraparound to their loads), and the weight of the second
    in float32."""
    g = f - 0.5
    k = math.floor(g)
    i = int(k)
    return np.uint64(min(max(i, 0), n - 1)), np.uint64(min(max(i + 1, 0), n - 1)), np.float32(g - k)


@serial
def pixel_texels(p0, p1, scale, n):
    """The texels [t0, t1) of a level of n texels (scale of them per full-resolution pixel) that bilinear taps at
    the centres of pixels p0..p1 along one axis read (_axis of the first and the last)."""
    return int(_axis((p0 + 0.5) * scale, n)[0]), int(_axis((p1 + 0.5) * scale, n)[1]) + 1


@serial
def _corners(o, w, ax, ay):
    """A bilinear tap's texels on a level (first texel o, width w) between axes ax and ay, top left, top right,
    bottom left, bottom right, and its weights across and down."""
    i0, i1, a = ax
    j0, j1, b = ay
    top, bottom = np.uint64(o) + j0 * np.uint64(w), np.uint64(o) + j1 * np.uint64(w)
    return top + i0, top + i1, bottom + i0, bottom + i1, a, b


@serial
def _bilinear(data, o, w, ax, ay):
    """Colour and depth of a level (first texel o, width w) between the texels of axes ax and ay, in the
    pyramid's float32 (simd.texel_blend: each texel one vector load, the blend four lanes at once)."""
    k00, k01, k10, k11, a, b = _corners(o, w, ax, ay)
    return texel_blend(data, k00, k01, k10, k11, a, b)


@kernel
def _pull_level(pyramid, k):
    """Level k from level k - 1: the weighted mean of each texel's valid children (summed in the order top left,
    top right, bottom left, bottom right; simd.texel_mean), a child past an odd level's edge not counted.
    Unsigned indices: numba adds no negative-index wraparound to their loads."""
    data = pyramid.data
    o_fine, wf, hf = pyramid.offsets[k - 1], pyramid.widths[k - 1], pyramid.heights[k - 1]
    o_coarse, wc, hc = pyramid.offsets[k], pyramid.widths[k], pyramid.heights[k]
    for y in nb.prange(hc):
        down = 2 * y + 1 < hf
        top, bottom = np.uint64(o_fine + 2 * y * wf), np.uint64(o_fine + min(2 * y + 1, hf - 1) * wf)
        row = np.uint64(o_coarse + y * wc)
        for x in range(wc):
            left_x, right_x = np.uint64(2 * x), np.uint64(min(2 * x + 1, wf - 1))
            j = row + np.uint64(x)
            texel_mean(data, top + left_x, top + right_x, bottom + left_x, bottom + right_x, 2 * x + 1 < wf, down, j)


class LevelSamples(NamedTuple):
    """Level 0's samples listed, for a pull-push that reads them in place of level 0's texels and writes them there:
    which texels they are, their texel indices (row-major, ascending) and each texel row's first, and their colour
    and depth (weight 1; every other texel of level 0 weight 0, whatever it holds)."""

    mask: np.ndarray  # (texels of level 0,) bool
    texels: np.ndarray  # (n,) int64
    starts: np.ndarray  # (height + 1,) int64: row y's samples are [starts[y], starts[y + 1])
    rgb: np.ndarray  # (n, 3) float32
    depth: np.ndarray  # (n,) float32


@kernel
def _pull_samples(pyramid, samples, sums):
    """Level 1 from level 0's samples (LevelSamples): the mean of each texel's, as _pull_level takes it with weights
    1 and 0 (the same sums: the children that count added in the same order, those that do not adding 0). Reads the
    samples' 16 bytes each in place of every texel of level 0 (20 bytes, most of them not samples where they are
    sparse). A texel without samples gets weight 0 and colour and depth 0, which no pull or push reads. `sums`: a row
    of scratch per numba thread."""
    data = pyramid.data
    texels, starts, rgb, depth = samples.texels, samples.starts, samples.rgb, samples.depth
    wf, hf = pyramid.widths[0], pyramid.heights[0]
    o_coarse, wc, hc = pyramid.offsets[1], pyramid.widths[1], pyramid.heights[1]
    for y in nb.prange(hc):
        row = sums[nb.get_thread_id()]
        for c in range(CHANNELS):
            for x in range(wc):
                row[c, x] = 0.0
        for fine in range(2 * y, min(2 * y + 2, hf)):  # the top children, then the bottom ones
            first = fine * wf
            for s in range(starts[fine], starts[fine + 1]):
                x = (texels[s] - first) // 2
                row[0, x] += rgb[s, 0]
                row[1, x] += rgb[s, 1]
                row[2, x] += rgb[s, 2]
                row[DEPTH, x] += depth[s]
                row[WEIGHT, x] += 1.0
        for c in range(WEIGHT):  # the means, a channel at a time with selects: the divisions vectorise
            for x in range(wc):
                wsum = row[WEIGHT, x]
                row[c, x] /= wsum if wsum > 0.0 else 1.0
        o = np.uint64(o_coarse + y * wc)
        for x in range(wc):
            j = o + np.uint64(x)
            data[j, 0], data[j, 1], data[j, 2] = row[0, x], row[1, x], row[2, x]
            data[j, DEPTH], data[j, WEIGHT] = row[DEPTH, x], min(1.0, row[WEIGHT, x])


class Columns(NamedTuple):
    """Scratch for a pull-push, sized for level 0 (push_columns): for the push, the coarser level's two texel
    columns either side of each finer texel's centre and the second one's weight (_axis), one entry per column of
    the finer level, and per numba thread (nb.get_thread_id()) the columns of a row's texels that miss weight; for a
    pull from level 0's samples (_pull_samples), per thread a row of level 1's sums."""

    col0: np.ndarray  # (width,) uint64
    col1: np.ndarray  # (width,) uint64
    weight: np.ndarray  # (width,) float32
    holes: np.ndarray  # (threads, width) uint32
    sums: np.ndarray  # (threads, CHANNELS, level 1's width) float64


def push_columns(width: int) -> Columns:
    """Scratch for pull_push on pyramids whose level 0 is `width` texels wide, to keep across frames."""
    threads = nb.config.NUMBA_NUM_THREADS
    holes, sums = np.empty((threads, width), np.uint32), np.empty((threads, CHANNELS, (width + 1) // 2))
    return Columns(np.empty(width, np.uint64), np.empty(width, np.uint64), np.empty(width, np.float32), holes, sums)


@serial
def _push_row(data, row, wf, mask, col0, col1, col_weight, o_coarse, wc, ay, holes):
    """Fill the missing weight of the wf texels of a row (its first texel `row`) from the coarser level (first
    texel o_coarse, wc wide) between its texel rows ay. The row's texels that miss weight are listed first, without
    a branch (`holes`: a row of scratch), then filled: a branch per texel on its weight mispredicts where samples
    are sparse (level 0's push took 1.15-1.35x as long at rift_s)."""
    n = 0
    for x in range(wf):
        holes[n] = x
        n += _weight(data, row + np.uint64(x), mask) < 1.0
    for h in range(n):
        x = holes[h]
        i = row + np.uint64(x)
        w = _weight(data, i, mask)
        ax = (col0[x], col1[x], col_weight[x])
        if w > 0.0:
            r, g, b, d = _bilinear(data, o_coarse, wc, ax, ay)
            v = 1.0 - w
            r, g = w * data[i, 0] + v * r, w * data[i, 1] + v * g
            b, d = w * data[i, 2] + v * b, w * data[i, DEPTH] + v * d
            data[i, 0], data[i, 1], data[i, 2], data[i, DEPTH] = r, g, b, d
        else:  # the coarser level's colour and depth as they are, stored as one vector
            k00, k01, k10, k11, a, b = _corners(o_coarse, wc, ax, ay)
            texel_blend_into(data, k00, k01, k10, k11, a, b, i)
        data[i, WEIGHT] = 1.0


@serial
def _place_row(data, samples, y):
    """Level 0's samples of row y (LevelSamples) into their texels, weight 1."""
    texels, rgb, depth = samples.texels, samples.rgb, samples.depth
    for s in range(samples.starts[y], samples.starts[y + 1]):
        i = np.uint64(texels[s])
        data[i, 0], data[i, 1], data[i, 2] = rgb[s, 0], rgb[s, 1], rgb[s, 2]
        data[i, DEPTH], data[i, WEIGHT] = depth[s], 1.0


@serial
def _place(pyramid, samples):
    """Level 0's samples into their texels, row by row: for a pyramid of one level, which no push fills."""
    for y in range(pyramid.heights[0]):
        _place_row(pyramid.data, samples, y)


@kernel
def _push_level(pyramid, k, samples, columns):
    """Fill the missing weight of level k's texels from level k + 1, bilinearly; the columns' taps are taken once
    per level (into `columns`), the rows' once per row. With `samples` (level 0's, LevelSamples), their mask stands
    for level 0's weights and each row's samples are written into their texels too, while the row is in the cache.
    Unsigned indices: numba adds no negative-index wraparound to their loads and stores."""
    data = pyramid.data
    o_fine, wf, hf = pyramid.offsets[k], pyramid.widths[k], pyramid.heights[k]
    o_coarse, wc, hc = pyramid.offsets[k + 1], pyramid.widths[k + 1], pyramid.heights[k + 1]
    sx, sy = wc / wf, hc / hf
    col0, col1, col_weight, holes = columns.col0, columns.col1, columns.weight, columns.holes
    for x in range(wf):
        col0[x], col1[x], col_weight[x] = _axis((x + 0.5) * sx, wc)
    for y in nb.prange(hf):
        ay = _axis((y + 0.5) * sy, hc)
        row, scratch = np.uint64(o_fine + y * wf), holes[nb.get_thread_id()]
        if samples is None:
            _push_row(data, row, wf, None, col0, col1, col_weight, o_coarse, wc, ay, scratch)
        else:
            _push_row(data, row, wf, samples.mask, col0, col1, col_weight, o_coarse, wc, ay, scratch)
            _place_row(data, samples, np.int64(y))


def pull_push(pyramid: Pyramid, samples: LevelSamples | None = None, columns: Columns | None = None) -> None:
    """Fill every texel of level 0 from its valid samples (weight > 0), in place, coarse levels too.

    samples, when given, lists level 0's samples (weight 1, every other texel 0) in place of level 0's texels: a
    frame's samples need not clear the others' weights nor be written into level 0 first. Level 1 is pulled from the
    list, and level 0's push writes them into their texels as it fills the others.
    columns: push_columns(level 0's width), kept by callers that run every frame (else made here)."""
    columns = push_columns(int(pyramid.widths[0])) if columns is None else columns
    if len(columns.col0) < pyramid.widths[0]:
        raise ValueError(f"columns hold {len(columns.col0)} texels, level 0 has {pyramid.widths[0]}")
    if len(pyramid.offsets) == 1 and samples is not None:  # a 1x1 image: nothing to pull or push
        _place(pyramid, samples)
    for k in range(1, len(pyramid.offsets)):
        if k == 1 and samples is not None:
            _pull_samples(pyramid, samples, columns.sums)
        else:
            _pull_level(pyramid, k)
    for k in range(len(pyramid.offsets) - 2, -1, -1):
        _push_level(pyramid, k, samples if k == 0 else None, columns)


class RowSamples(NamedTuple):
    """sample_row's scratch, one row per numba thread (nb.get_thread_id()): a row's levels, then its samples, and
    the two texel rows of a level and of the next one blended vertically."""

    levels: np.ndarray  # (threads, width) float64
    values: np.ndarray  # (threads, width, 3) float64: colour
    texels: np.ndarray  # (threads, 2, width, 3) float32: colour
    runs: np.ndarray  # (threads, width + 1, 2) int64: a row's runs of pixels on one level

    @classmethod
    def empty(cls, width: int) -> RowSamples:
        threads = nb.config.NUMBA_NUM_THREADS
        return cls(
            np.zeros((threads, width)),
            np.zeros((threads, width, 3)),
            np.zeros((threads, 2, width, 3), np.float32),
            np.zeros((threads, width + 1, 2), np.int64),
        )


@serial
def _vertical(data, first, second, weight, n, out):
    """Colour of n texels, texel rows from flat indices first and second blended by weight, into out."""
    q = np.float32(1.0) - weight
    for c in range(n):
        i, j = first + np.uint64(c), second + np.uint64(c)
        out[c, 0] = q * data[i, 0] + weight * data[j, 0]
        out[c, 1] = q * data[i, 1] + weight * data[j, 1]
        out[c, 2] = q * data[i, 2] + weight * data[j, 2]


@serial
def level_runs(levels, n, top, runs):
    """The runs of one integer level among levels[:n], each clamped to `top` (a negative one: -1, not read): each
    run's first index and level into runs (at least (n + 1, 2) int64), its end the next one's first (runs[count, 0]
    is n). Returns the count and the lowest and highest level read (top and -1 when none): a pass per level then
    visits its runs, not every element."""
    count, lo, hi, current, ftop = 0, top, -1, -2, float(top)
    for i in range(n):
        k = int(min(levels[i], ftop)) if levels[i] >= 0.0 else -1
        if k != current:
            runs[count, 0], runs[count, 1], current = i, k, k
            count += 1
            if k >= 0:
                lo, hi = min(lo, k), max(hi, k)
    runs[count, 0] = n
    return count, lo, hi


@serial
def sample_row(data, widths, axes, y, levels, values, texels, runs):
    """values[x] = colour at the centre of full-resolution pixel (x, y) on level levels[x] (fractional,
    clamped to the top level), trilinearly, of the pyramid with `data` and level widths `widths`, for every pixel
    of row y whose level is >= 0; the others are left as they are (levels and values: at least a row long).
    `axes`: its PixelAxes (pixel_axes); `texels`: a (2, width, 3) float32 scratch; `runs`: a (width + 1, 2) int64
    scratch. One pass per integer level the row holds, over the runs of pixels on that level (listed in a first
    scan): a pass keeps one level's tables and constants out of its loop, where a loop that picks each pixel's level
    reloads them per pixel (2.5x slower at rift_s). Each pass blends the next level's two texel rows about y once
    per texel (the first pass its own level's too; the others have it from the pass before), then each pixel blends
    two of those: two taps per pixel and level, not four. Level 0 is the texel itself."""
    col0, col1, col_weight, row0, row1, row_weight = axes
    top = len(widths) - 1
    width, ftop = col0.shape[1], float(top)
    n, lo, hi = level_runs(levels, width, top, runs)
    first = np.uint64(y * width)
    for k in range(lo, hi + 1):
        up = min(k + 1, top)  # blended in where the level has a fraction (not above the top one)
        k0, k1, kw, u0, u1, uw = col0[k], col1[k], col_weight[k], col0[up], col1[up], col_weight[up]
        here, above = texels[k % 2], texels[(k + 1) % 2]  # the pass before blended this level as its next one
        if k == lo and k > 0:
            _vertical(data, row0[k, y], row1[k, y], row_weight[k, y], widths[k], here)
        if k < top:
            _vertical(data, row0[up, y], row1[up, y], row_weight[up, y], widths[up], above)
        for run in range(n):
            if runs[run, 1] != k:
                continue
            for x in range(runs[run, 0], runs[run + 1, 0]):
                level = min(levels[x], ftop)
                if k == 0:
                    i = first + np.uint64(x)
                    r, g, b = data[i, 0], data[i, 1], data[i, 2]
                else:
                    r, g, b = rgb_blend(here, k0[x], k1[x], kw[x])
                if k < top:  # level - k is 0 on integer levels, where this adds 0 to finite values
                    values[x, 0], values[x, 1], values[x, 2] = rgb_lerp_to_blend(
                        r, g, b, above, u0[x], u1[x], uw[x], level - k
                    )
                else:
                    values[x, 0], values[x, 1], values[x, 2] = r, g, b


@inline
def _quincunx_axes(w, h, sx, sy, off, x, y):
    """The axes of weier2018 Figure 3's taps on a level of w x h texels (sx and sy of them per full-resolution
    pixel) around full-resolution pixel coordinates (x, y), `off` full-resolution pixels apart diagonally: x - off,
    x and x + off across, then the same down."""
    x, y, off_x, off_y = x * sx, y * sy, off * sx, off * sy
    return _axis(x - off_x, w), _axis(x, w), _axis(x + off_x, w), _axis(y - off_y, h), _axis(y, h), _axis(y + off_y, h)


@inline
def _trilinear(data, o, w, ax, ay, o_up, w_up, bx, by, t):
    """A tap t of the way from the bilinear tap between axes ax and ay of one level (first texel o, width w) to the
    one between bx and by of another (simd.texel_trilinear)."""
    k00, k01, k10, k11, a, b = _corners(o, w, ax, ay)
    m00, m01, m10, m11, c, d = _corners(o_up, w_up, bx, by)
    return texel_trilinear(data, k00, k01, k10, k11, a, b, m00, m01, m10, m11, c, d, t)


@inline
def quincunx(data, lower, upper, t, off, x, y):
    """weier2018 Figure 3's five taps (the centre, then the diagonals) around full-resolution pixel coordinates
    (x, y), `off` full-resolution pixels apart diagonally, each t of the way from a pyramid level to the next:
    `lower` and `upper` each a level's first texel, width, height and texels per full-resolution pixel across and
    down. Each tap's colour and depth in float64; t = 0 reads the lower level alone, as u + 0 (u - u). Taps in line
    share an axis."""
    o, w, h, sx, sy = lower
    xm, xc, xp, ym, yc, yp = _quincunx_axes(w, h, sx, sy, off, x, y)
    if t == 0.0:
        o_up, w_up, um, uc, up, vm, vc, vp = o, w, xm, xc, xp, ym, yc, yp
    else:
        o_up, w_up, h_up, sx_up, sy_up = upper
        um, uc, up, vm, vc, vp = _quincunx_axes(w_up, h_up, sx_up, sy_up, off, x, y)
    return (
        _trilinear(data, o, w, xc, yc, o_up, w_up, uc, vc, t),
        _trilinear(data, o, w, xm, ym, o_up, w_up, um, vm, t),
        _trilinear(data, o, w, xp, ym, o_up, w_up, up, vm, t),
        _trilinear(data, o, w, xm, yp, o_up, w_up, um, vp, t),
        _trilinear(data, o, w, xp, yp, o_up, w_up, up, vp, t),
    )


@serial
def quincunx_offset(level):
    """The diagonal offset of the quincunx taps on `level`, in full-resolution pixels: half a texel there."""
    return 0.5 * 2.0 ** max(level, 0.0)
