"""The SIMD intrinsics against the same arithmetic written channel by channel: bit for bit."""

import ctypes
import mmap

import numba as nb
import numpy as np
import pytest

from hmdrt.foveation.stages.pyramid import DEPTH, WEIGHT
from hmdrt.kernels.simd import (
    rgb_accumulate,
    rgb_bilinear,
    rgb_bilinear_add,
    rgb_blend,
    rgb_lerp_to_blend,
    texel_blend,
    texel_blend_into,
    texel_mean,
    texel_trilinear,
)


@nb.njit(cache=True)
def _by_channel(data, k00, k01, k10, k11, a, b):
    p, q = np.float32(1.0) - a, np.float32(1.0) - b
    out = np.empty(4, np.float32)
    for lane, c in enumerate((0, 1, 2, DEPTH)):
        out[lane] = q * (p * data[k00, c] + a * data[k01, c]) + b * (p * data[k10, c] + a * data[k11, c])
    return out


@nb.njit(cache=True)
def _corners(taps, i):
    return np.uint64(taps[i, 0]), np.uint64(taps[i, 1]), np.uint64(taps[i, 2]), np.uint64(taps[i, 3])


@nb.njit(cache=True)
def _blend_all(data, taps, weights, simd, out):
    for i in range(taps.shape[0]):
        k00, k01, k10, k11 = _corners(taps, i)
        a, b = weights[i, 0], weights[i, 1]
        if simd:
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = texel_blend(data, k00, k01, k10, k11, a, b)
        else:
            out[i] = _by_channel(data, k00, k01, k10, k11, a, b)


def test_texel_blend_is_the_channel_by_channel_blend_bit_for_bit():
    rng = np.random.default_rng(3)
    data = (rng.standard_normal((500, 5)) * 1e3).astype(np.float32)
    data[::7, DEPTH] = np.inf  # misses' depth
    data[::5, WEIGHT] = -7.0  # the weight channel is never read
    taps = rng.integers(0, len(data), (20000, 4))
    weights = rng.random((20000, 2)).astype(np.float32)
    weights[:100] = 0.0
    weights[100:200] = 1.0
    simd, scalar = np.empty((20000, 4), np.float32), np.empty((20000, 4), np.float32)
    _blend_all(data, taps, weights, True, simd)
    _blend_all(data, taps, weights, False, scalar)
    assert np.array_equal(simd.view(np.uint32), scalar.view(np.uint32))
    # the last texel's first four floats are within the array: no read past it
    last = np.uint64(len(data) - 1)
    assert texel_blend_at(data, last) == pytest.approx(tuple(data[-1, :4]))


@nb.njit(cache=True)
def _trilinear_all(data, taps, weights, ts, simd, out):
    for i in range(taps.shape[0]):
        k00, k01, k10, k11 = _corners(taps, i)
        m00, m01, m10, m11 = _corners(taps[:, 4:], i)
        a, b, c, d, t = weights[i, 0], weights[i, 1], weights[i, 2], weights[i, 3], ts[i]
        if simd:
            out[i, 0], out[i, 1], out[i, 2], out[i, 3] = texel_trilinear(
                data, k00, k01, k10, k11, a, b, m00, m01, m10, m11, c, d, t
            )
        else:
            u, v = _by_channel(data, k00, k01, k10, k11, a, b), _by_channel(data, m00, m01, m10, m11, c, d)
            for lane in range(4):
                out[i, lane] = u[lane] + t * (v[lane] - u[lane])


def test_texel_trilinear_is_the_lerp_of_two_blends_channel_by_channel_bit_for_bit():
    """Two texel blends and the float64 lerp between them (t 0, 1 and between; inf depths among the texels), against
    the blends channel by channel and the lerp written lane by lane: v - u in float32, the rest in float64. NaN
    where both depths are inf, in either."""
    rng = np.random.default_rng(9)
    data = (rng.standard_normal((500, 5)) * 1e3).astype(np.float32)
    data[::7, DEPTH] = np.inf
    taps = rng.integers(0, len(data), (20000, 8))
    weights = rng.random((20000, 4)).astype(np.float32)
    ts = rng.random(20000)
    ts[:100], ts[100:200] = 0.0, 1.0
    taps[:100, 4:] = taps[:100, :4]  # t = 0 with the same taps twice, as quincunx reads a whole level
    weights[:100, 2:] = weights[:100, :2]
    simd, scalar = np.empty((20000, 4)), np.empty((20000, 4))
    _trilinear_all(data, taps, weights, ts, True, simd)
    _trilinear_all(data, taps, weights, ts, False, scalar)
    assert np.array_equal(np.isnan(simd), np.isnan(scalar))  # inf - inf in a depth lane, whichever NaN it makes
    finite = ~np.isnan(scalar)
    assert np.array_equal(simd[finite].view(np.uint64), scalar[finite].view(np.uint64))


@nb.njit(cache=True)
def _blend_into_all(data, taps, weights, out):
    for i in range(taps.shape[0]):
        k00, k01, k10, k11 = _corners(taps, i)
        texel_blend_into(data, k00, k01, k10, k11, weights[i, 0], weights[i, 1], out + i)


def test_texel_blend_into_stores_the_blend_as_the_texels_colour_and_depth():
    """texel_blend_into writes texel_blend's four lanes into a texel's r, g, b and depth, and nothing else: its
    weight and the texels around it stay as they were."""
    rng = np.random.default_rng(5)
    data = (rng.standard_normal((700, 5)) * 1e3).astype(np.float32)
    data[::7, DEPTH] = np.inf
    taps = rng.integers(0, 500, (200, 4))
    weights = rng.random((200, 2)).astype(np.float32)
    before = data.copy()
    expected = np.empty((200, 4), np.float32)
    _blend_all(data, taps, weights, True, expected)
    _blend_into_all(data, taps, weights, 500)
    assert np.array_equal(data[500:, :4].view(np.uint32), expected.view(np.uint32))
    assert np.array_equal(data[500:, WEIGHT], before[500:, WEIGHT])
    assert np.array_equal(data[:500], before[:500])


@nb.njit(cache=True)
def _mean_by_channel(data, ks, present, j):
    wsum, sums = 0.0, np.zeros(4)
    for n in range(4):
        k, here = ks[n], present[n]
        w = data[k, WEIGHT] if here and data[k, WEIGHT] > 0.0 else np.float32(0.0)
        wsum += w
        for lane, c in enumerate((0, 1, 2, DEPTH)):
            sums[lane] += w * data[k, c] if w > 0.0 else 0.0
    if wsum > 0.0:
        for lane, c in enumerate((0, 1, 2, DEPTH)):
            data[j, c] = sums[lane] / wsum
    data[j, WEIGHT] = min(1.0, wsum)


@nb.njit(cache=True)
def _means(simd, scalar, taps, flags, first):
    """Texel first + i of `simd` by texel_mean and of `scalar` by _mean_by_channel, from the children taps[i]."""
    for i in range(taps.shape[0]):
        ks, right, down = _corners(taps, i), flags[i, 0], flags[i, 1]
        texel_mean(simd, ks[0], ks[1], ks[2], ks[3], right, down, first + i)
        _mean_by_channel(scalar, ks, (True, right, down, right and down), first + i)


def test_texel_mean_is_the_pull_channel_by_channel_bit_for_bit():
    """texel_mean against the weighted mean written channel by channel: children of weight 0 or below, of NaN
    weight or absent count for nothing, whatever their channels hold (NaN, inf); no child counted leaves the
    texel's colour and depth as they were and its weight 0."""
    rng = np.random.default_rng(6)
    data = (rng.standard_normal((600, 5)) * 1e3).astype(np.float32)
    data[:400, WEIGHT] = np.where(rng.random(400) < 0.4, 0.0, rng.random(400)).astype(np.float32)
    data[:400:9, WEIGHT] = np.nan
    data[1:400:11, WEIGHT] = -1.0
    data[2:400:13, 0] = np.nan
    data[3:400:7, DEPTH] = np.inf
    taps = rng.integers(0, 400, (200, 4))
    taps[:20] = np.flatnonzero(data[:400, WEIGHT] == 0.0)[:4]  # nothing counted
    flags = rng.random((200, 2)) < 0.7
    simd, scalar = data.copy(), data.copy()
    _means(simd, scalar, taps, flags, 400)
    assert np.array_equal(simd.view(np.uint32), scalar.view(np.uint32))
    assert (simd[400:420, WEIGHT] == 0.0).all() and np.array_equal(simd[400:420, :4], data[400:420, :4])


@nb.njit(cache=True)
def texel_blend_at(data, k):
    return texel_blend(data, k, k, k, k, np.float32(0.5), np.float32(0.5))


def test_texel_blend_refuses_other_layouts():
    data = np.zeros((4, 5), np.float64)
    with pytest.raises(nb.core.errors.TypingError):
        texel_blend_at(data, np.uint64(0))
    with pytest.raises(nb.core.errors.TypingError):
        texel_blend_at(np.zeros((5, 4), np.float32).T, np.uint64(0))


@nb.njit(cache=True)
def _accumulate_all(data, weights, simd, out):
    for t in range(data.shape[0] // 3):
        i = np.uint64(3 * t)
        r, g, b, w = np.float64(t), -0.5 * t, 1e-3, weights[t]
        if simd:
            out[t, 0], out[t, 1], out[t, 2] = rgb_accumulate(r, g, b, w, data, i)
        else:
            out[t, 0], out[t, 1], out[t, 2] = r + w * data[i], g + w * data[i + 1], b + w * data[i + 2]


def test_rgb_accumulate_is_the_channel_by_channel_sum_bit_for_bit_to_the_last_texel():
    """Every texel of an RGB image read flat, the last one too (its fourth lane reads the spare float after the
    array), against the same multiply and add written channel by channel."""
    rng = np.random.default_rng(5)
    data = np.empty(3 * 999 + 1, np.float32)[:-1]  # with a spare float after the last texel, as rgb_accumulate needs
    data[:] = rng.standard_normal(3 * 999) * 1e3
    data[::11] = np.inf
    weights = rng.random(999)
    weights[::7] = 0.0
    simd, scalar = np.empty((999, 3)), np.empty((999, 3))
    _accumulate_all(data, weights, True, simd)
    _accumulate_all(data, weights, False, scalar)
    assert np.array_equal(simd.view(np.uint64), scalar.view(np.uint64))


@nb.njit(cache=True)
def _bilinear_all(image, taps, weights, simd, out):
    flat = image.reshape(-1)
    for t in range(taps.shape[0]):
        i, step_x, step_y = np.uint64(taps[t, 0]), np.uint64(taps[t, 1]), np.uint64(taps[t, 2])
        a, b = weights[t, 0], weights[t, 1]
        if simd:
            out[t, 0], out[t, 1], out[t, 2] = rgb_bilinear(image, i, step_x, step_y, a, b)
            continue
        w00, w01, w10, w11 = (1.0 - a) * (1.0 - b), a * (1.0 - b), (1.0 - a) * b, a * b
        for c in range(3):
            k = i + np.uint64(c)
            out[t, c] = (
                w00 * flat[k] + w01 * flat[k + step_x] + w10 * flat[k + step_y] + w11 * flat[k + step_y + step_x]
            )


@nb.njit(cache=True)
def _bilinear_sums(image, taps, weights, fades, simd, sums):
    flat = image.reshape(-1)
    for t in range(taps.shape[0]):
        i, step_x, step_y = np.uint64(taps[t, 0]), np.uint64(taps[t, 1]), np.uint64(taps[t, 2])
        a, b, fade, s = weights[t, 0], weights[t, 1], fades[t], 4 * (t % 7)
        if simd:
            rgb_bilinear_add(sums, s, fade, image, i, step_x, step_y, a, b)
            continue
        w00, w01, w10, w11 = (1.0 - a) * (1.0 - b), a * (1.0 - b), (1.0 - a) * b, a * b
        sums[s + 3] += fade
        for c in range(3):
            k = i + np.uint64(c)
            tap = w00 * flat[k] + w01 * flat[k + step_x] + w10 * flat[k + step_y] + w11 * flat[k + step_y + step_x]
            sums[s + c] += fade * tap


def _guarded(texels: int) -> tuple[np.ndarray, mmap.mmap]:
    """A (texels, 3) float32 array that ends where an unreadable page begins: a read past its last float faults."""
    page = mmap.PAGESIZE
    size = -(-texels * 12 // page) * page
    pages = mmap.mmap(-1, size + page)
    libc = ctypes.CDLL(None, use_errno=True)
    base = ctypes.addressof(ctypes.c_char.from_buffer(pages))
    assert libc.mprotect(ctypes.c_void_p(base + size), page, 0) == 0  # PROT_NONE
    return np.frombuffer(pages, np.float32, texels * 3, size - texels * 12).reshape(texels, 3), pages


def test_rgb_bilinear_is_the_channel_by_channel_tap_bit_for_bit_and_reads_nothing_past_the_image():
    """Taps over a 20 x 50 RGB image (inf and NaN among its channels, weights 0 and 1 among theirs), clamped at its
    border as bilinear_footprint clamps them, the last texel among their corners, against the same products and
    sums written channel by channel; the image ends at an unreadable page, so a load past its last float faults.
    Then rgb_bilinear_add's weighted sums of the same taps against the sums written channel by channel."""
    h, w, n = 20, 50, 5000
    rng = np.random.default_rng(8)
    image, pages = _guarded(h * w)
    image[:] = rng.standard_normal((h * w, 3)) * 1e3
    image[::11, 0] = np.inf
    image[5::13, 2] = np.nan
    x, y = rng.integers(0, w, n), rng.integers(0, h, n)
    x[:50], y[:50] = w - 1, h - 1  # the last texel, every step clamped to 0
    taps = np.stack([3 * (y * w + x), np.where(x < w - 1, 3, 0), np.where(y < h - 1, 3 * w, 0)], 1)
    weights = rng.random((n, 2))
    weights[50:100] = 0.0
    weights[100:150] = 1.0
    simd, scalar = np.empty((n, 3)), np.empty((n, 3))
    _bilinear_all(image, taps, weights, True, simd)
    _bilinear_all(image, taps, weights, False, scalar)
    assert np.array_equal(simd.view(np.uint64), scalar.view(np.uint64))
    # rgb_bilinear_add: the same taps weighted into seven running sums of four (colour, then the weights' sum), over
    # finite texels, so that every sum stays a number to compare bit for bit
    image[~np.isfinite(image)] = 7.0
    fades = rng.random(n)
    fades[::9] = 0.0
    simd_sums, scalar_sums = np.ones(28), np.ones(28)
    _bilinear_sums(image, taps, weights, fades, True, simd_sums)
    _bilinear_sums(image, taps, weights, fades, False, scalar_sums)
    assert np.isfinite(scalar_sums).all()
    assert np.array_equal(simd_sums.view(np.uint64), scalar_sums.view(np.uint64))
    del image
    pages.close()


@nb.njit(cache=True)
def _row_lerps(rows, taps, weights, ts, simd, out):
    for i in range(taps.shape[0]):
        i0, i1, j0, j1 = taps[i, 0], taps[i, 1], taps[i, 2], taps[i, 3]
        a, c, t = weights[i, 0], weights[i, 1], ts[i]
        if simd:
            r, g, b = rgb_blend(rows, i0, i1, a)
            out[i, 0], out[i, 1], out[i, 2] = rgb_lerp_to_blend(r, g, b, rows, j0, j1, c, t)
            out[i, 3], out[i, 4], out[i, 5] = r, g, b
            continue
        p, q = np.float32(1.0) - a, np.float32(1.0) - c
        for ch in range(3):
            x = p * rows[i0, ch] + a * rows[i1, ch]
            v = q * rows[j0, ch] + c * rows[j1, ch]
            out[i, ch], out[i, 3 + ch] = x + t * (v - x), x


def test_rgb_blend_and_its_lerp_are_channel_by_channel_bit_for_bit_to_the_last_texel():
    """rgb_blend and rgb_lerp_to_blend (pyramid.sample_row's steps) against the same float32 blends and float64 lerp
    written channel by channel, over texels that end at an unreadable page (the last one among the taps)."""
    rng = np.random.default_rng(10)
    rows, pages = _guarded(400)
    rows[:] = rng.standard_normal((400, 3)) * 1e3
    taps = rng.integers(0, 400, (5000, 4))
    taps[:50] = 399
    weights = rng.random((5000, 2)).astype(np.float32)
    weights[50:100] = 0.0
    ts = rng.random(5000)
    ts[100:150] = 0.0
    simd, scalar = np.empty((5000, 6)), np.empty((5000, 6))
    _row_lerps(rows, taps, weights, ts, True, simd)
    _row_lerps(rows, taps, weights, ts, False, scalar)
    assert np.array_equal(simd.view(np.uint64), scalar.view(np.uint64))
    del rows
    pages.close()
