"""Numerical stability at the edges: weier2016 section 3.4, the running estimate (alpha, rho) and k(dt)."""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest

from hmdrt.foveation.stages.reproject import MeshImage, _distances
from hmdrt.foveation.stages.temporal import AGES, age_table, k_at, k_of_age, running_estimate
from hmdrt.foveation.weier16.buffers import CacheRule, Final, RowTaps, Samples, Selection, Support, SupportGrid
from hmdrt.foveation.weier16.cache import _update
from hmdrt.foveation.weier16.params import COVERED, TRACED
from hmdrt.kernels.schedule import dynamic
from hmdrt.optics.projection import camera_arrays
from tests.stability.common import (
    camera,
)


@pytest.mark.parametrize("rho", [0.0, -1.0, 1e-300, 1e-12])
def test_running_estimate_with_rho_tending_to_0_takes_the_new_sample_whole(rho):
    alpha, rho_new = running_estimate(rho, 0.1)
    # alpha = alpha' = 1 / (rho + 1) and rho_t = (alpha^2 + (1 - alpha)^2 / rho)^-1 = rho + 1, both -> 1; at rho <= 0
    # (nothing accumulated) the limit itself, where (1 - alpha)^2 / rho would be 0 / 0
    assert alpha == pytest.approx(1.0 / (1.0 + max(rho, 0.0)), rel=1e-15)
    assert rho_new == pytest.approx(1.0 + max(rho, 0.0), rel=1e-12)


@pytest.mark.parametrize("k", [0.05, 0.1, 0.5])
def test_running_estimate_with_rho_tending_to_infinity_settles_at_k_and_one_over_k_squared(k):
    for rho in (1e12, 1e300, math.inf):
        alpha, rho_new = running_estimate(rho, k)
        assert alpha == pytest.approx(k, rel=1e-12) and rho_new == pytest.approx(1.0 / (k * k), rel=1e-9)


def test_running_estimate_with_alpha_1_restarts_and_alpha_0_keeps_everything_without_dividing_by_zero():
    for rho in (1.0, 7.0, 1e9):
        assert running_estimate(rho, 1.0) == (1.0, 1.0)  # k = 1: only the new sample counts
    assert running_estimate(math.inf, 0.0) == (0.0, math.inf)  # alpha = 0: the cache is kept, its count unbounded
    alpha, rho = running_estimate(1e300, 0.0)
    assert alpha == pytest.approx(1e-300) and rho == pytest.approx(1e300)  # rho_t = rho_{t-1} + 1


def test_k_of_age_with_k_min_equal_to_k_max_is_that_constant():
    for dt in (0.0, 1.0, 2.0, 14.0, 15.0, 1e9):
        for t_max in (1.0, 2.0, 15.0):
            assert k_of_age(dt, 0.3, 0.3, t_max) == pytest.approx(0.3, rel=1e-15)


def test_k_of_age_with_t_max_1_is_k_max_instead_of_dividing_by_zero():
    assert k_of_age(1.0, 0.1, 0.8, 1.0) == 0.8 and k_of_age(5.0, 0.1, 0.8, 1.0) == 0.8
    for t_max in (1.0 + 1e-15, 1.0 + 1e-9):  # just above: finite and within the bounds
        for dt in (1.0, 1.5, 2.0):
            assert 0.1 - 1e-15 <= k_of_age(dt, 0.1, 0.8, t_max) <= 0.8


def test_k_of_age_at_dt_0_is_k_min_and_far_beyond_t_max_is_k_max():
    """Ages count frames from 1: dt = 0 (the same frame number again) or dt < 0 (frames numbered afresh) take
    k_min, where the formula would fall below the bound it is."""
    k_min, k_max, t_max = 0.1, 1.0, 15.0
    for dt in (-1e12, -5.0, 0.0, 0.5, 1.0):
        assert k_of_age(dt, k_min, k_max, t_max) == pytest.approx(k_min, rel=1e-15)
    for dt in (t_max, 100.0, 1e12, 1e300):
        assert k_of_age(dt, k_min, k_max, t_max) == k_max
    x0, x1 = math.log(k_min), math.log(k_max)
    assert k_of_age(8.0, k_min, k_max, t_max) == pytest.approx(math.exp(x0 + 7.0 / 14.0 * (x1 - x0)))


@pytest.mark.parametrize(("k_min", "k_max", "t_max"), [(0.1, 0.5, 30.0), (0.05, 1.0, 15.0), (0.2, 0.8, 1.0)])
def test_k_at_reads_the_age_table_with_the_bits_of_k_of_age(k_min, k_max, t_max):
    """The cache update reads k(dt) from a table at whole ages (an exp a sample cost a sixth of a still view's
    update): the same bits as the formula at every whole age in it, and the formula itself past it or between."""
    ages = np.empty(AGES)
    age_table(k_min, k_max, t_max, ages)
    for dt in [*range(-3, AGES + 5), 2.5, 1e9, -1e12]:
        assert k_at(ages, float(dt), k_min, k_max, t_max) == k_of_age(float(dt), k_min, k_max, t_max), dt
    assert k_at(ages, 7.0, k_min, k_max, t_max) == ages[7]
    ages[7] = -1.0  # read from the table, not computed
    assert k_at(ages, 7.0, k_min, k_max, t_max) == -1.0


def accumulate(frames: int, k: float = 0.1, size: int = 4, seed: int = 0, in_place: bool = False):
    """weier2016's cache update (the real kernel, float32 colour and cache info) over `frames` frames of a still
    view in which every pixel is traced each frame, alternating two sample colours a, b per pixel; k_min = k_max = k.
    in_place: the final buffers updated in place, as the method does where the mesh reprojects every pixel onto
    itself, else written into the other of two. Returns a, b, and the (colour, cache info) after the last two
    frames."""
    n = size * size
    rng = np.random.default_rng(seed)
    a, b = rng.random((n, 3), dtype=np.float32), rng.random((n, 3), dtype=np.float32)
    cam = camera(size, size)
    ys, xs = np.mgrid[0:size, 0:size] + 0.5
    mesh = MeshImage(np.stack([xs, ys]).astype(np.float32), np.full((size, size), 0.5, np.float32))  # unmoved, 2 m
    tx = cam.tan_left + xs * (cam.tan_right - cam.tan_left) / size
    ty = cam.tan_up - ys * (cam.tan_up - cam.tan_down) / size
    depth = (2.0 * np.sqrt(tx * tx + ty * ty + 1.0)).astype(np.float32).reshape(n)  # the mesh's surface
    zeros = np.zeros((n, 3), np.float32)
    rows = np.full(size, size)
    selection = Selection(np.full((size, size), TRACED, np.uint8), rows, np.arange(size + 1) * size, rows * 0, rows * 0)
    finals = (Final.empty(size, size), Final.empty(size, size))
    image = np.empty((size, size, 3), np.float32)
    taps = RowTaps.empty(size)
    distance = np.empty((size, size), np.float32)  # what CoarseMesh.distances measures, read in place
    _distances(camera_arrays(cam), mesh.zinv, distance)
    ages = np.empty(AGES)
    age_table(k, k, 15.0, ages)
    last = []
    threads = numba.get_num_threads()
    numba.set_num_threads(1)  # 16 pixels: starting the thread pool each frame would cost 100x the work
    try:
        for t in range(frames):
            previous, final = (finals[0], finals[0]) if in_place else (finals[t % 2], finals[(t + 1) % 2])
            samples = Samples(a if t % 2 == 0 else b, depth, zeros, zeros)
            rule = CacheRule(float(t), k, k, 15.0, 0.05, 4, 0, False, in_place and t > 0, ages)
            dynamic(
                _update,
                selection,
                mesh,
                camera_arrays(cam),
                distance,
                previous,
                samples,
                Support.empty(size, size),  # every pixel traced: nothing merged from it
                SupportGrid.of(size, size, size, size),
                rule,
                taps,
                final,
                image,
            )
            selection.flags[:] = TRACED | COVERED
            if t >= frames - 2:
                last.append((final.color.reshape(n, 3).copy(), final.info.reshape(n, 3).copy()))
    finally:
        numba.set_num_threads(threads)
    return a, b, last


def check_accumulation(frames: int, k: float = 0.1) -> None:
    a, b, ((c_a, s_a), (c_b, s_b)) = accumulate(frames, k)
    if frames % 2:  # the last frame took a
        (c_a, s_a), (c_b, s_b) = (c_b, s_b), (c_a, s_a)
    a, b = a.astype(np.float64), b.astype(np.float64)
    # the two-cycle of c = k s + (1 - k) c: c_a = (k a + k (1 - k) b) / (1 - (1 - k)^2), likewise c_b
    den = 1.0 - (1.0 - k) ** 2
    bound = 2.0**-24 / k * 4  # float32 rounding of each step, 0.5 ulp, amplified by 1 / k; no growth with frames
    np.testing.assert_allclose(c_a, (k * a + k * (1 - k) * b) / den, atol=bound, rtol=0)
    np.testing.assert_allclose(c_b, (k * b + k * (1 - k) * a) / den, atol=bound, rtol=0)
    for s in (s_a, s_b):
        np.testing.assert_allclose(s[:, 0], k, rtol=1e-6)  # alpha = max(alpha', k) = k
        np.testing.assert_allclose(s[:, 1], (2.0 - k) / k, rtol=1e-5)  # rho's fixed point, bounded in float32
    assert s_b[0, 2] == frames - 1 or s_a[0, 2] == frames - 1  # frame numbers exact in float32 below 2^24


def test_float32_accumulation_over_10_thousand_frames_stays_at_the_closed_form():
    check_accumulation(10_000)


def test_the_cache_updated_in_place_accumulates_as_into_the_other_buffer():
    _, _, swapped = accumulate(101)
    _, _, in_place = accumulate(101, in_place=True)
    for (color, info), (color_in_place, info_in_place) in zip(swapped, in_place, strict=True):
        np.testing.assert_array_equal(color_in_place, color)
        np.testing.assert_array_equal(info_in_place, info)


def test_accumulation_with_k_1_is_exactly_the_newest_sample():
    a, b, ((c_1, _), (c_2, _)) = accumulate(11, k=1.0)
    np.testing.assert_array_equal(c_1, b)  # frame 9 took b
    np.testing.assert_array_equal(c_2, a)
