"""Numerical stability at the edges: weier2016's foveal function p(e) and weier2018's sampling tables."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmdrt.errors import ConfigError
from hmdrt.foveation import MethodChoice, make_method
from hmdrt.foveation.rrm import RrmParams, foveal_rectangle
from hmdrt.foveation.stages.sampling import (
    bernoulli_mask,
    expected_fraction,
    foveal_config,
    foveal_probability,
    sampling_tables,
    table_mask,
    transition_points,
)
from hmdrt.scene import load_scene
from hmdrt.spatial import gaze_direction
from hmdrt.trace.integrator import Whitted
from tests.stability.common import (
    FORWARD,
    camera,
    empty_scene,
    falloff,
    render_frames,
)


@pytest.mark.parametrize("p_min", [0.0, 1.0])
def test_foveal_function_with_p_min_0_or_1_matches_its_closed_form_and_traces_none_or_all_of_the_periphery(p_min):
    r0, r1 = 5.0, 10.0
    for e in (0.0, 4.999, 5.0, 7.5, 9.999, 10.0, 90.0, 180.0):
        assert foveal_probability(e, r0, r1, p_min) == pytest.approx(float(falloff(e, r0, r1, p_min)), abs=1e-15)
    cam = camera()
    ecc = cam.eccentricity(gaze_direction(5.0, -3.0))
    cfg = foveal_config("small", None, None, p_min)
    assert expected_fraction(ecc, cfg) == pytest.approx(falloff(ecc, r0, r1, p_min).mean(), rel=1e-12)
    for frame in range(3):
        mask = bernoulli_mask(ecc, cfg, seed=7, frame=frame)
        assert mask[ecc < r0].all()
        periphery = mask[ecc >= r1]
        assert periphery.size > 1000 and (periphery.all() if p_min == 1.0 else not periphery.any())


def test_foveal_function_with_r0_equal_to_r1_is_a_step_with_no_transition_samples():
    r = 10.0
    assert foveal_probability(r - 1e-12, r, r, 0.2) == 1.0 and foveal_probability(r, r, r, 0.2) == 0.2
    cam = camera()
    g = gaze_direction(3.0, 2.0)
    ecc = cam.eccentricity(g)
    cfg = foveal_config("medium", r, r, 0.2)
    assert expected_fraction(ecc, cfg) == pytest.approx(np.where(ecc < r, 1.0, 0.2).mean(), rel=1e-12)
    tables = sampling_tables(cam, cfg, seed=1)
    assert tables.samples == 0  # equation (1) has no band to fill
    np.testing.assert_array_equal(table_mask(cam, g, ecc, cfg, tables), np.where(ecc < r, True, tables.s_out))


def test_foveal_function_with_r0_greater_than_r1_is_an_error():
    with pytest.raises(ConfigError, match="must not exceed"):
        foveal_config("medium", 30.0, 20.0, None)
    with pytest.raises(ConfigError, match="r0 must not exceed r1"):
        MethodChoice.parse("weier18", r0=30.0, r1=20.0)
    with Whitted(empty_scene()) as tracer, pytest.raises(ConfigError, match="must not exceed"):
        make_method("weier16", tracer, r0=30.0, r1=20.0)


@pytest.mark.parametrize(
    ("r0", "r1", "p_min", "match"),
    [(math.nan, 20.0, 0.1, "angles"), (5.0, -1.0, 0.1, "angles"), (5.0, 10.0, 1.5, "p_min"), (5, 10, -0.1, "p_min")],
)
def test_foveal_function_with_nan_negative_or_out_of_range_values_is_an_error(r0, r1, p_min, match):
    with pytest.raises(ConfigError, match=match):
        foveal_config("medium", r0, r1, p_min)


def test_method_options_with_nan_radii_are_an_error():
    for method in ("weier16", "weier18"):
        with pytest.raises(ConfigError):
            MethodChoice.parse(f"{method}?r0=nan")


def test_foveal_function_with_r0_0_falls_off_from_the_gaze_itself():
    cfg = foveal_config("medium", 0.0, 20.0, 0.05)
    assert foveal_probability(0.0, 0.0, 20.0, 0.05) == 1.0
    assert foveal_probability(10.0, 0.0, 20.0, 0.05) == pytest.approx(1.0 - 0.95 * 0.5)
    cam = camera()
    g = gaze_direction(-4.0, 6.0)
    ecc = cam.eccentricity(g)
    assert expected_fraction(ecc, cfg) == pytest.approx(falloff(ecc, 0.0, 20.0, 0.05).mean(), rel=1e-12)
    tables = sampling_tables(cam, cfg, seed=2)
    ry, rx = tables.s_in.shape[0] // 2, tables.s_in.shape[1] // 2
    oy, ox = np.mgrid[-ry : ry + 1, -rx : rx + 1]
    r_deg = np.hypot(ox / tables.ppd[0], oy / tables.ppd[1])
    band = r_deg < 20.0
    assert tables.samples == round((1.0 - 0.95 * r_deg[band] / 20.0).sum())  # M of the whole disc
    mask = table_mask(cam, g, ecc, cfg, tables)
    assert mask.shape == ecc.shape and mask[ecc >= 20.0].tolist() == tables.s_out[ecc >= 20.0].tolist()


def test_foveal_function_with_r1_180_deg_covers_the_sphere_and_its_tables_stay_finite():
    cfg = foveal_config("medium", 10.0, 180.0, 0.1)
    assert foveal_probability(95.0, 10.0, 180.0, 0.1) == pytest.approx(1.0 - 0.9 * 85.0 / 170.0)
    assert foveal_probability(180.0, 10.0, 180.0, 0.1) == pytest.approx(0.1)
    cam = camera(32, 32)
    tables = sampling_tables(cam, cfg, seed=3)
    assert tables.s_in.shape == (
        2 * (math.ceil(180.0 * tables.ppd[1]) + 1) + 1,
        2 * (math.ceil(180.0 * tables.ppd[0]) + 1) + 1,
    )
    points = transition_points(cfg, tables.samples, tables.ppd)
    r = np.hypot(points[:, 0] / tables.ppd[0], points[:, 1] / tables.ppd[1])
    assert np.all(np.isfinite(points)) and r.min() >= 10.0 - 1e-9 and r.max() < 180.0 + 1e-9
    g = gaze_direction(0.0, 0.0)
    ecc = cam.eccentricity(g)
    mask = table_mask(cam, g, ecc, cfg, tables)
    # equation (1) as printed asks for more than a sample per pixel out to far beyond this image's 45 degrees
    assert mask[ecc < 10.0].all() and mask.mean() > 0.9


def test_gaze_at_the_frustum_edge_and_beyond_keeps_true_eccentricities():
    cam = camera(32, 32)  # +-45 degrees horizontally
    edge = gaze_direction(45.0, 0.0)
    assert cam.gaze_pixel(edge)[0] == pytest.approx(32.0, abs=1e-9)  # on the right edge
    beyond = gaze_direction(70.0, 0.0)
    x = cam.gaze_pixel(beyond)[0]
    assert x == pytest.approx((math.tan(math.radians(70.0)) + 1.0) / 2.0 * 32.0, rel=1e-12) and x > 32
    xy = np.array([[31.5, 16.0], [0.5, 16.0]], np.float32)
    for g in (edge, beyond):
        # the true angle between a pixel's ray and the gaze, not a pixel distance
        for px, e in zip(xy[:, 0], cam.eccentricity(g, xy), strict=True):
            ray = np.array([cam.tan_left + px * (cam.tan_right - cam.tan_left) / 32, 0.0, -1.0])
            assert e == pytest.approx(math.degrees(math.acos(ray @ g / np.linalg.norm(ray))), abs=1e-4)
        cfg = foveal_config("medium", None, None, 0.1)
        ecc = cam.eccentricity(g)
        tables = sampling_tables(cam, cfg)
        mask = table_mask(cam, g, ecc, cfg, tables)
        assert mask[ecc < 10.0].all() and np.array_equal(mask[ecc >= 20.0], tables.s_out[ecc >= 20.0])
    images, _ = render_frames(load_scene("whitted"), "weier16", [edge, beyond, beyond])
    assert all(np.isfinite(im).all() for im in images)


@pytest.mark.parametrize("gaze", [(1.0, 0.0, 0.0), (0.0, 0.0, 1.0), tuple(gaze_direction(150.0, 10.0))])
def test_gaze_at_or_beyond_90_degrees_off_axis_puts_the_point_of_regard_off_the_image(gaze):
    """At 90 degrees the point of regard is at infinity, behind the eye project() would mirror it onto the image:
    gaze_pixel puts it 1e6 tangent units out instead, so nothing placed around it lands on the image."""
    g = np.array(gaze)
    cam = camera(16, 16)
    por = cam.gaze_pixel(g)
    assert np.all(np.isfinite(por)) and np.abs(por).max() > 1e6
    x0, x1, y0, y1 = foveal_rectangle(cam, g, RrmParams())
    assert (x1 - x0) * (y1 - y0) == 0  # no foveal rectangle on the image
    cfg = foveal_config("medium", 10.0, 180.0, 0.2)
    tables = sampling_tables(cam, cfg, seed=4)
    ecc = cam.eccentricity(g)
    assert ecc.min() > 40.0
    # S_in is read in angle space around the gaze: the pixels, all in the transition band, get equation (1)'s
    # density as printed there (a quarter to a half at 60-130 degrees), not S_out's
    assert 0.05 < table_mask(cam, g, ecc, cfg, tables).mean() < 0.8
    for method, options in (("rrm", {}), ("weier18", {"r1": 180.0}), ("kim21", {}), ("weier16", {})):
        images, stats = render_frames(load_scene("whitted"), method, [g, g], **options)
        assert all(np.isfinite(im).all() for im in images), method
        if method == "weier18":  # every pixel in the transition band, at equation (1)'s density there
            assert 0.05 < stats[-1].metrics["sample_fraction"] < 0.8


def test_gaze_exactly_at_a_pixel_corner_gives_the_four_pixels_around_it_one_eccentricity():
    cam = camera(32, 32)
    por = cam.gaze_pixel(FORWARD)
    np.testing.assert_array_equal(por, [16.0, 16.0])  # the corner shared by pixels (15, 15) .. (16, 16)
    ecc = cam.eccentricity(FORWARD)
    four = ecc[15:17, 15:17]
    sx = (cam.tan_right - cam.tan_left) / 32
    sy = (cam.tan_up - cam.tan_down) / 32
    np.testing.assert_allclose(four, math.degrees(math.atan(math.hypot(sx / 2, sy / 2))), rtol=1e-5)
    cfg = foveal_config("small", None, None, 0.01)
    tables = sampling_tables(cam, cfg, seed=5)
    for nudge in (-1e-9, 0.0, 1e-9):  # either side of the corner: the addressing pixel changes, p(e) does not
        g = FORWARD + np.array([nudge, nudge, 0.0])
        mask = table_mask(cam, g, cam.eccentricity(g), cfg, tables)
        assert mask[15:17, 15:17].all()
        assert bernoulli_mask(cam.eccentricity(g), cfg, 0, 0)[15:17, 15:17].all()
