"""Numerical stability at the edges: weier2018 equation (3), thin-lens circles of confusion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmdrt.foveation.stages.dof import (
    DOF_PRESETS,
    IMAGE_DISTANCE_MM,
    circle_of_confusion,
    coc_map,
    focal_lengths,
    layered_blur,
)
from hmdrt.foveation.stages.pyramid import DEPTH, WEIGHT, Pyramid, pull_push
from hmdrt.scene import Scene, load_scene
from hmdrt.scene.model import Material
from hmdrt.scene.shapes import quad
from hmdrt.spatial import Pose as HeadPose
from tests.stability.common import (
    FORWARD,
    SKY,
    render_frames,
)

K, E = DOF_PRESETS["medium"]


def coc_closed_form(g: float, d_o_m: float, t_m: float = 0.2) -> float:
    """CoC = (V(f, g) - V(f, d)) k V(f, g) E with V(F, G) = F G / (G - F); V(f, d) = d_i by the choice of f."""
    d_n, d_f = d_o_m * 1000 - t_m * 1000, d_o_m * 1000 + t_m * 1000
    if d_n <= g <= d_f:
        return 0.0
    d = d_n if g < d_n else d_f
    f = 1.0 / (1.0 / d + 1.0 / IMAGE_DISTANCE_MM)
    v = f if math.isinf(g) else f * g / (g - f)
    return (v - IMAGE_DISTANCE_MM) * K * v * E


def coc(g: float, d_o_m: float, t_m: float = 0.2) -> float:
    return circle_of_confusion(g, *focal_lengths(d_o_m, t_m), K, E)


def test_coc_at_or_inside_the_focal_length_is_the_finite_largest_near_blur():
    """g <= f has no real image (G > F in equation (3)): the CoC of g = f (1 + 1e-9) is used, positive, finite and
    larger than at any other distance; the blur caps it at MAX_BLUR_PX and weier18 counts the capped pixels."""
    d_n, d_f, f_n, f_f = focal_lengths(1.5)
    g_clamp = f_n * (1.0 + 1e-9)
    v = f_n * g_clamp / (g_clamp - f_n)
    expected = (v - IMAGE_DISTANCE_MM) * K * v * E
    for g in (f_n, 0.5 * f_n, 1e-3, 0.0):
        assert coc(g, 1.5) == pytest.approx(expected, rel=1e-6) and math.isfinite(coc(g, 1.5))
    assert expected > max(coc(g, 1.5) for g in (f_n * 1.01, 100.0, 1000.0, 1e9, math.inf))
    coc_px = coc_map(np.array([[0.0, 1e-6, 1.5, math.inf]]), 1.5, DOF_PRESETS["medium"], 14.2)
    assert np.all(np.isfinite(coc_px)) and coc_px[0, 0] == coc_px[0, 1] > 0 and coc_px[0, 2] == 0
    # a wall 2 um in front of the eye (g -> 0): the blur stays finite and the capped pixels are counted
    wall = Scene("wall", [quad("q", (-1, -1, -2e-6), (2, 0, 0), (0, 2, 0), "m")], {"m": Material()}, background=SKY)
    wall.start = HeadPose.looking((0.0, 0.0, 0.0))
    images, stats = render_frames(wall, "weier18", [FORWARD, FORWARD], dof="strong")
    assert all(np.isfinite(im).all() for im in images)
    assert stats[-1].metrics["coc_capped_pixels"] > 0 and math.isfinite(stats[-1].metrics["coc_max_px"])


@pytest.mark.parametrize("d_o", [0.75, 1.5, 6.0])
def test_coc_tends_to_0_at_d_n_and_d_f_from_both_sides(d_o):
    d_n, d_f, _, _ = focal_lengths(d_o)
    for edge in (d_n, d_f):
        assert coc(edge, d_o) == 0.0
        for rel in (1e-3, 1e-6, 1e-9):
            outside = edge * (1 - rel) if edge == d_n else edge * (1 + rel)
            inside = edge * (1 + rel) if edge == d_n else edge * (1 - rel)
            assert coc(inside, d_o) == 0.0
            value = coc(outside, d_o)
            assert value == pytest.approx(coc_closed_form(outside, d_o), rel=1e-6, abs=1e-12)
            assert (value > 0) == (edge == d_n) and abs(value) < 2e4 * rel  # linear in the distance to the edge


def test_coc_with_focus_within_t_keeps_d_n_at_twice_the_image_distance():
    """d_o <= t would make d_n = d_o - t zero or negative: d_n is kept at 2 d_i, where f_n = d_i 2/3 < d_n."""
    for d_o in (0.2, 0.1, 1e-6):
        d_n, d_f, f_n, f_f = focal_lengths(d_o, 0.2)
        assert d_n == 2 * IMAGE_DISTANCE_MM and f_n == pytest.approx(2 * IMAGE_DISTANCE_MM / 3)
        assert d_f == pytest.approx(max(d_o * 1000 + 200, d_n)) and f_f < d_f
        assert coc(d_n, d_o) == 0.0 and coc(d_f, d_o) == 0.0 and coc(d_n * 0.99, d_o) > 0
    d_n, d_f, f_n, f_f = focal_lengths(0.0, 0.0)  # no ZeroDivisionError: d_f is kept at d_n
    assert d_n == d_f == 2 * IMAGE_DISTANCE_MM and f_n == f_f
    assert coc(d_n * 2, 0.0, 0.0) < 0 < coc(d_n / 1.5, 0.0, 0.0)


def test_coc_with_focus_at_infinity_is_finite_and_all_nearer_objects_are_near_field():
    d_n, d_f, f_n, f_f = focal_lengths(math.inf)
    assert (d_n, d_f, f_n, f_f) == (math.inf, math.inf, IMAGE_DISTANCE_MM, IMAGE_DISTANCE_MM)
    for g in (100.0, 1e4, 1e9):
        v = IMAGE_DISTANCE_MM * g / (g - IMAGE_DISTANCE_MM)
        assert coc(g, math.inf) == pytest.approx((v - IMAGE_DISTANCE_MM) * K * v * E, rel=1e-9)
        assert coc(g, math.inf) > 0
    assert coc(math.inf, math.inf) == 0.0
    px = coc_map(np.array([[0.5, 6.0, math.inf]]), math.inf, DOF_PRESETS["medium"], 14.2)
    assert np.all(np.isfinite(px)) and px[0, 0] > px[0, 1] > 0 and px[0, 2] == 0


def test_coc_as_g_tends_to_infinity_approaches_the_focal_plane_limit():
    limit = coc_closed_form(math.inf, 1.5)
    assert limit < 0 and coc(math.inf, 1.5) == pytest.approx(limit, rel=1e-12)
    for g in (1e8, 1e12, 1e300):
        # V(f, g) = f / (1 - f / g), and V - d_i is about f / 80: a relative error near 80 f / g
        assert coc(g, 1.5) == pytest.approx(limit, rel=1e4 / g + 1e-12)


def test_weier18_depth_inaccuracy_widens_the_focus_range_and_a_clamped_near_limit_is_counted():
    depth = np.array([[0.9, 1.0, 1.2, 3.0, 6.0]])
    tight = coc_map(depth, 1.0, DOF_PRESETS["medium"], 14.2, 0.0)
    wide = coc_map(depth, 1.0, DOF_PRESETS["medium"], 14.2, 5.0)  # d_o <= t: d_n kept at 2 d_i
    assert np.all(tight[0, [0, 2, 3, 4]] != 0) and np.all(wide == 0.0)
    scene = load_scene("whitted")
    _, narrow = render_frames(scene, "weier18", [FORWARD] * 2, depth_inaccuracy_m=0.0)
    _, broad = render_frames(scene, "weier18", [FORWARD] * 2, depth_inaccuracy_m=50.0)
    assert narrow[-1].metrics["coc_max_px"] != broad[-1].metrics["coc_max_px"]  # the parameter reaches the CoC
    assert narrow[-1].metrics["focus_near_clamped"] == 0 and broad[-1].metrics["focus_near_clamped"] == 1


@pytest.mark.parametrize("far", [-5.0, -1e10, -1e30, -3.4e38])
def test_layered_blur_with_huge_cocs_caps_the_blur_and_stays_a_convex_mix(far):
    """Near CoCs of 2.5e20 px (g <= f) and far ones up to float32's limit: every blur radius is capped at
    MAX_BLUR_PX before it becomes an integer, and each output pixel stays a weighted mean of input colours."""
    rng = np.random.default_rng(2)
    color = rng.random((48, 16, 3), dtype=np.float32)
    coc_px = np.zeros((48, 16), np.float32)
    coc_px[:4] = 2.5e20
    coc_px[4:8] = far
    ecc = np.full((48, 16), 5.0, np.float32)
    ecc[:, 8:] = 40.0  # the right half in the periphery (pyramid blur), the left in central vision (Gaussian)
    pyramid = Pyramid.empty(16, 48)
    pyramid.data.fill(0.0)
    level0 = pyramid.data[: 48 * 16]
    level0[:, :3], level0[:, WEIGHT], level0[:, DEPTH] = color.reshape(-1, 3), 1.0, 1.0
    pull_push(pyramid)
    out = layered_blur(color, coc_px, ecc, 10.0, 20.0, pyramid)
    assert np.all(np.isfinite(out))
    assert np.all(out >= color.min(axis=(0, 1)) - 1e-6) and np.all(out <= color.max(axis=(0, 1)) + 1e-6)
    np.testing.assert_array_equal(out[32:], color[32:])  # in focus, beyond the near blur's reach: unchanged
