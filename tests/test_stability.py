"""Numerical stability (issue 6): at the edges of every formula, filter and integrator the code gives finite output
that matches a closed form, a clear error (ConfigError, HmdrtError, ValueError), or a documented clamp that is
counted; never NaN or inf, a crash, or a silently wrong answer. Heavy runs are in test_stability_slow.py (-m slow),
each with a short sibling here."""

from __future__ import annotations

import math
from decimal import Decimal, localcontext

import msgspec
import numba
import numpy as np
import pytest

from drivers.clocksync import ClockSync
from drivers.fusion import GRAVITY, OrientationFusion
from hmdrt.bus.messages import Gaze, Pose
from hmdrt.compositor.samples import SampleStore
from hmdrt.errors import ConfigError, SceneError
from hmdrt.foveation import METHODS, FrameRequest, MethodChoice, make_method
from hmdrt.foveation.kim21 import Kim21Params, bezier_controls, tau_fov_array
from hmdrt.foveation.rrm import RrmParams, foveal_rectangle
from hmdrt.foveation.stages.dof import (
    DOF_PRESETS,
    IMAGE_DISTANCE_MM,
    circle_of_confusion,
    coc_map,
    focal_lengths,
    layered_blur,
)
from hmdrt.foveation.stages.gaze import FixationFilter
from hmdrt.foveation.stages.pyramid import Pyramid, pull_push
from hmdrt.foveation.stages.reproject import MeshImage
from hmdrt.foveation.stages.sampling import (
    bernoulli_mask,
    expected_fraction,
    foveal_config,
    foveal_probability,
    sampling_tables,
    table_mask,
    transition_points,
    transition_radius,
)
from hmdrt.foveation.stages.temporal import History, exponential_smoothing, k_of_age, running_estimate
from hmdrt.foveation.weier16 import COVERED, TRACED, CacheRule, Final, Samples, Selection, _update
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.optics.profiles import HmdProfile
from hmdrt.optics.projection import camera_arrays
from hmdrt.scene import Scene, load_scene
from hmdrt.scene.model import Material, Mesh, PointLight
from hmdrt.scene.pack import pack
from hmdrt.scene.shapes import box, quad, sphere
from hmdrt.spatial import Pose as HeadPose
from hmdrt.spatial import gaze_direction, parse_gaze, quat_from_yaw_pitch
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.bsdf import fresnel_dielectric, refract, split
from hmdrt.trace.integrator import Whitted
from hmdrt.trace.tracer import Tracer

from .helpers import trace_gbuffer

MS = 1_000_000
FORWARD = np.array([0.0, 0.0, -1.0])
SKY = (0.3, 0.5, 0.8)


def camera(width: int = 64, height: int = 64, pose: HeadPose | None = None, centred: bool = False) -> EyeCamera:
    """A sim-cpu eye (90 x 94 degrees, symmetric) at a small resolution; centred: at the head (IPD 0)."""
    profile = get_profile("sim-cpu").with_resolution(width, height)
    if centred:
        profile = msgspec.structs.replace(profile, ipd_mm=0.0)
    return EyeCamera.for_eye(profile, pose or HeadPose())


def empty_scene() -> Scene:
    return Scene("empty", [], {"m": Material()}, background=SKY)


def render_frames(scene: Scene, method: str, gazes, width: int = 16, height: int = 16, **options):
    """Consecutive frames of the left eye through a method, one per gaze: (images, stats)."""
    profile = get_profile("sim-cpu").with_resolution(width, height)
    images, stats = [], []
    with Whitted(scene) as tracer:
        m = make_method(method, tracer, **options)
        cam = EyeCamera.for_eye(profile, scene.start)
        for frame, g in enumerate(gazes):
            s = FrameStats()
            images.append(m.render(FrameRequest(cam, np.asarray(g, dtype=np.float64), frame, 0), s))
            stats.append(s)
    return images, stats


def falloff(e: np.ndarray, r0: float, r1: float, p_min: float) -> np.ndarray:
    """weier2016's p(e) written out: 1 below r0, linear to p_min at r1, p_min beyond."""
    e = np.asarray(e, dtype=np.float64)
    ramp = 1.0 - (1.0 - p_min) * (e - r0) / (r1 - r0) if r1 > r0 else np.full_like(e, p_min)
    return np.where(e < r0, 1.0, np.where(e >= r1, p_min, ramp))


# ---------------------------------------------------------------------------------------------------------------
# weier2016's foveal function p(e) and weier2018's sampling tables
# ---------------------------------------------------------------------------------------------------------------


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
    np.testing.assert_array_equal(
        table_mask(ecc, cfg, tables, cam.gaze_pixel(g)), np.where(ecc < r, True, tables.s_out)
    )


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
    mask = table_mask(ecc, cfg, tables, cam.gaze_pixel(g))
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
    mask = table_mask(ecc, cfg, tables, cam.gaze_pixel(g))
    assert mask[ecc < 10.0].all() and 0.1 < mask.mean() < 1.0


def test_transition_pixels_beyond_the_reach_of_s_in_take_s_out_rather_than_no_sample():
    """S_in spans r1 at the centre's pixel density; off-axis the image plane stretches angles, so part of the
    transition band lies beyond it. Those pixels take S_out (density p_min), never less than the periphery."""
    cam = camera(64, 64)
    cfg = foveal_config("large", None, None, 0.1)  # r1 = 30 deg
    tables = sampling_tables(cam, cfg, seed=6)
    g = gaze_direction(30.0, 25.0)
    ecc = cam.eccentricity(g)
    por = np.floor(cam.gaze_pixel(g)).astype(int)
    ry, rx = tables.s_in.shape[0] // 2, tables.s_in.shape[1] // 2
    y, x = np.mgrid[0:64, 0:64]
    reach = (np.abs(y - por[1]) <= ry) & (np.abs(x - por[0]) <= rx)
    band = (ecc >= cfg.r0) & (ecc < cfg.r1)
    assert (band & ~reach).sum() > 20  # a real part of the band
    mask = table_mask(ecc, cfg, tables, cam.gaze_pixel(g))
    np.testing.assert_array_equal(mask[band & ~reach], tables.s_out[band & ~reach])
    inside = band & reach
    np.testing.assert_array_equal(mask[inside], tables.s_in[(y - por[1] + ry)[inside], (x - por[0] + rx)[inside]])


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
        mask = table_mask(ecc, cfg, tables, cam.gaze_pixel(g))
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
    # S_in cannot reach the pixels: they take S_out's density rather than no sample at all
    np.testing.assert_array_equal(table_mask(ecc, cfg, tables, por), tables.s_out)
    for method, options in (("rrm", {}), ("weier18", {"r1": 180.0}), ("kim21", {}), ("weier16", {})):
        images, stats = render_frames(load_scene("whitted"), method, [g, g], **options)
        assert all(np.isfinite(im).all() for im in images), method
        if method == "weier18":  # every pixel in the transition band, sampled through S_out at p_min = 0.2
            assert 0.05 < stats[-1].metrics["sample_fraction"] < 0.4


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
        mask = table_mask(cam.eccentricity(g), cfg, tables, cam.gaze_pixel(g))
        assert mask[15:17, 15:17].all()
        assert bernoulli_mask(cam.eccentricity(g), cfg, 0, 0)[15:17, 15:17].all()


# ---------------------------------------------------------------------------------------------------------------
# weier2018 equation (1): r = r0 + (r1 - r0) (sqrt((p^2 - 1) u + 1) - 1) / (p - 1)
# ---------------------------------------------------------------------------------------------------------------


def _printed_equation_1(u: float, p: float, digits: int = 60) -> float:
    """Equation (1) as printed, in 60-digit decimal arithmetic: the reference away from p = 1."""
    with localcontext() as ctx:
        ctx.prec = digits
        du, dp = Decimal(u), Decimal(p)
        return float((((dp * dp - 1) * du + 1).sqrt() - 1) / (dp - 1))


@pytest.mark.parametrize("p_min", [0.0, 1e-300, 0.05, 0.5, 1.0 - 1e-12, 1.0])
def test_equation_1_at_u_0_and_1_gives_exactly_r0_and_r1(p_min):
    r = transition_radius(np.array([0.0, 1.0]), 10.0, 20.0, p_min)
    assert r[0] == 10.0 and r[1] == pytest.approx(20.0, abs=1e-12)


def test_equation_1_as_p_min_tends_to_1_follows_the_series_instead_of_0_over_0():
    u = np.linspace(0.0, 1.0, 21)
    np.testing.assert_array_equal(transition_radius(u, 0.0, 1.0, 1.0), u)  # the limit p = 1: uniform
    for eps in (1e-2, 1e-4, 1e-8, 1e-12, 1e-15):
        x = transition_radius(u, 0.0, 1.0, 1.0 - eps)
        # x = u - eps u (1 - u) / 2 - eps^2 u^2 (1 - u) / 2 + O(eps^3)
        series = u - eps * u * (1 - u) / 2 - eps**2 * u * u * (1 - u) / 2
        np.testing.assert_allclose(x, series, atol=eps**3 + 4e-16)
        if eps >= 1e-8:
            reference = [_printed_equation_1(v, 1.0 - eps) for v in u]
            np.testing.assert_allclose(x, reference, atol=4e-16)


def test_equation_1_as_p_min_tends_to_0_is_the_inverse_cdf_of_a_linear_ramp():
    u = np.linspace(0.0, 1.0, 101)
    for p in (0.0, 1e-300, 1e-12):
        x = transition_radius(u, 0.0, 1.0, p)
        np.testing.assert_allclose(x, 1.0 - np.sqrt(1.0 - u), atol=1e-11)  # F(x) = 2x - x^2 inverted
    assert np.all(np.diff(transition_radius(u, 5.0, 10.0, 0.0)) > 0)  # monotone up to u = 1 (infinite slope)


# ---------------------------------------------------------------------------------------------------------------
# weier2016 section 3.4: running estimate (alpha, rho) and k(dt)
# ---------------------------------------------------------------------------------------------------------------


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


def accumulate(frames: int, k: float = 0.1, size: int = 4, seed: int = 0):
    """weier2016's cache update (the real kernel, float32 colour and cache info) over `frames` frames of a still
    view in which every pixel is traced each frame, alternating two sample colours a, b per pixel; k_min = k_max = k.
    Returns a, b, and the (colour, cache info) after the last two frames."""
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
    scratch = np.empty((numba.config.NUMBA_NUM_THREADS, size), np.float32)
    last = []
    threads = numba.get_num_threads()
    numba.set_num_threads(1)  # 16 pixels: starting the thread pool each frame would cost 100x the work
    try:
        for t in range(frames):
            previous, final = finals[t % 2], finals[(t + 1) % 2]
            samples = Samples(a if t % 2 == 0 else b, depth, zeros, zeros)
            rule = CacheRule(float(t), k, k, 15.0, 0.05, 4, 0, False)
            _update(
                selection,
                mesh,
                camera_arrays(cam),
                previous,
                samples,
                zeros.reshape(size, size, 3),
                rule,
                scratch,
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


def test_accumulation_with_k_1_is_exactly_the_newest_sample():
    a, b, ((c_1, _), (c_2, _)) = accumulate(11, k=1.0)
    np.testing.assert_array_equal(c_1, b)  # frame 9 took b
    np.testing.assert_array_equal(c_2, a)


# ---------------------------------------------------------------------------------------------------------------
# kim2021: tau_fov's Bezier segments and the temporal smoothing weights
# ---------------------------------------------------------------------------------------------------------------


def linear_case() -> Kim21Params:
    """Both quadratics' leading coefficients x0 - 2 x1 + x2 vanish: the tangents cross at the band midpoints."""
    return Kim21Params(
        e_f=4.0, e_p=5.0, e_m=10.0, e_np=12.0, e_max=20.0, tau_0=1.0, tau_f=3.0, tau_f_slope=1.0, tau_np=7.0
    )


def test_tau_fov_with_a_vanishing_leading_coefficient_is_solved_as_the_linear_case():
    ctrl = bezier_controls(linear_case())
    assert ctrl[0] - 2 * ctrl[1] + ctrl[2] == 0.0 and ctrl[6] - 2 * ctrl[7] + ctrl[8] == 0.0
    e = np.linspace(0.0, 4.0, 81)
    np.testing.assert_allclose(tau_fov_array(e, ctrl), 1.0 + e * e / 8.0, rtol=1e-14)  # t = e / 4
    e = np.linspace(4.0, 12.0, 81)
    t = (e - 4.0) / 8.0
    np.testing.assert_allclose(tau_fov_array(e, ctrl), 3.0 + 8.0 * t - 4.0 * t * t, rtol=1e-14)


@pytest.mark.parametrize("delta", [1e-13, 1e-9, -1e-9, 1e-6])
def test_tau_fov_next_to_the_linear_case_has_no_cancellation(delta):
    p = msgspec.structs.replace(linear_case(), tau_f_slope=1.0 + delta)
    ctrl = bezier_controls(p)
    e = np.linspace(0.0, 4.0, 41)
    tau = tau_fov_array(e, ctrl)
    assert np.all(np.isfinite(tau))
    np.testing.assert_allclose(tau, 1.0 + e * e / 8.0, atol=20 * abs(delta) + 1e-12)  # moves with delta, no more


def test_tau_fov_with_tau_f_slope_0_is_an_error_unless_the_function_is_flat():
    with pytest.raises(ConfigError, match="tau_f_slope must be positive"):
        bezier_controls(Kim21Params(tau_0=1.0, tau_f=2.0, tau_f_slope=0.0, tau_np=12.0))
    with pytest.raises(ConfigError, match="tau_f_slope must be positive"):
        bezier_controls(Kim21Params(tau_0=2.0, tau_f=2.0, tau_f_slope=0.0, tau_np=12.0))  # flat C1, rising C2
    flat = bezier_controls(Kim21Params(tau_0=3.0, tau_f=3.0, tau_f_slope=0.0, tau_np=3.0))
    np.testing.assert_allclose(tau_fov_array(np.linspace(-5.0, 90.0, 191), flat), 3.0, rtol=1e-15)


def test_tau_fov_at_exactly_e_f_and_e_np_takes_the_end_values_and_is_continuous_there():
    p = Kim21Params()
    ctrl = bezier_controls(p)
    at = tau_fov_array(np.array([0.0, p.e_f, p.e_np, p.e_np + 1.0, 180.0, -1.0]), ctrl)
    np.testing.assert_allclose(at, [p.tau_0, p.tau_f, p.tau_np, p.tau_np, p.tau_np, p.tau_0], rtol=1e-12)
    for edge, value in ((p.e_f, p.tau_f), (p.e_np, p.tau_np)):
        sides = tau_fov_array(np.array([np.nextafter(edge, 0.0), np.nextafter(edge, 99.0)]), ctrl)
        np.testing.assert_allclose(sides, value, rtol=1e-9)


def smoothing_history(colors: list[np.ndarray], cam: EyeCamera) -> History:
    history = History(4)
    depth = np.full((cam.height, cam.width), 2.0, np.float32)
    for c in colors:
        history.push(cam, depth, c)
    return history


@pytest.mark.parametrize("a", [0.0, 1e-30, 0.3, 1.0])
def test_kim21_smoothing_with_alpha_0_averages_the_frames_and_with_alpha_1_keeps_the_current_one(a):
    cam = camera(8, 8)
    rng = np.random.default_rng(1)
    c0, c1, c2 = (rng.random((8, 8, 3), dtype=np.float32) for _ in range(3))
    history = smoothing_history([c1, c2], cam)  # c2 is the newest earlier frame
    depth = np.full((8, 8), 2.0, np.float32)
    out = exponential_smoothing(cam, depth, c0, np.full((8, 8), a, np.float32), history, 4, 0.02)
    w = 1.0 - np.float32(a)  # the kernel sees alpha in float32
    expected = (c0 + w * c2 + w * w * c1) / (1.0 + w + w * w)  # sum a (1 - a)^i C_i / sum a (1 - a)^i, a -> 0 too
    np.testing.assert_allclose(out, expected, rtol=1e-5, atol=1e-6)


def test_kim21_alpha_above_1_is_an_error_and_alpha_0_renders_finite_frames():
    with pytest.raises(ConfigError, match="alpha"):
        MethodChoice.parse("kim21", alpha=[2.0, 0.8, 0.7, 0.5, 0.2, 0.1])
    images, _ = render_frames(load_scene("whitted"), "kim21", [FORWARD] * 3, alpha=[0.0] * 6, reuse=False)
    assert all(np.isfinite(im).all() for im in images)


# ---------------------------------------------------------------------------------------------------------------
# weier2018 equation (3): thin-lens circles of confusion
# ---------------------------------------------------------------------------------------------------------------

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
    level0[:, :3], level0[:, 3], level0[:, 4] = color.reshape(-1, 3), 1.0, 1.0
    pull_push(pyramid)
    out = layered_blur(color, coc_px, ecc, 10.0, 20.0, pyramid)
    assert np.all(np.isfinite(out))
    assert np.all(out >= color.min(axis=(0, 1)) - 1e-6) and np.all(out <= color.max(axis=(0, 1)) + 1e-6)
    np.testing.assert_array_equal(out[32:], color[32:])  # in focus, beyond the near blur's reach: unchanged


# ---------------------------------------------------------------------------------------------------------------
# geometry through the real Embree tracer and the Whitted integrator
# ---------------------------------------------------------------------------------------------------------------


def lambert(cam: EyeCamera, xy: np.ndarray, depth: np.ndarray, light: np.ndarray, intensity: float, normal, albedo):
    """Closed-form radiance of hits (depth along each pixel's ray): intensity cos / r^2 x albedo."""
    points = cam.position + depth[:, None].astype(np.float64) * cam.directions(xy).astype(np.float64)
    to_light = light - points
    r2 = np.einsum("ij,ij->i", to_light, to_light)
    cos = np.clip(to_light @ np.asarray(normal, float) / np.sqrt(r2), 0.0, None)
    return intensity * cos / r2 * np.asarray(albedo, float)[None, :].T


def test_sliver_and_degenerate_triangles_give_unit_normals_or_no_hit():
    """Slivers 2 m long and 2e-3 .. 2e-7 m wide, a line and a point triangle, in front of a backdrop."""
    slivers = []
    for i, aspect in enumerate((1e3, 1e5, 1e7)):
        y0, h = -0.6 + 0.6 * i, 2.0 / aspect
        v = np.array([[-1.0, y0, -2.0], [1.0, y0, -2.0], [1.0, y0 + h, -2.0]])
        slivers.append(Mesh(f"sliver{i}", v, np.array([[0, 1, 2]]), "m"))
    v = np.array([[0, 0, -2], [1, 0, -2], [2, 0, -2], [0, 1, -2], [0, 1, -2], [0, 1, -2]], float)
    degenerate = Mesh("deg", v, np.array([[0, 1, 2], [3, 4, 5]]), "m")
    backdrop = quad("back", (-5, -5, -3), (10, 0, 0), (0, 10, 0), "m")
    light = [PointLight(position=(0, 0, 1), intensity=(5, 5, 5))]
    scene = Scene("slivers", [*slivers, degenerate, backdrop], {"m": Material(specular=0.5)}, light)
    cam = camera(64, 64, centred=True)
    # every pixel centre, plus rays at each sliver's centroid (a third of its width from its edges)
    centroids = np.array([m.vertices.mean(axis=0) for m in slivers])
    xy = np.concatenate([pixel_centres(64, 64), cam.project(centroids)[0].astype(np.float32)])
    rgb, gbuf, _ = trace_gbuffer(scene, cam, xy)
    obj = gbuf.primary.object_id
    assert np.all(np.isfinite(rgb)) and np.all(obj >= 0)
    normals = gbuf.primary.normal_geometric
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(gbuf.primary.normal_shading, axis=1), 1.0, atol=1e-6)
    on_point = obj == 3  # a zero-area triangle, if Embree reports it at all, faces the ray
    np.testing.assert_allclose(normals[on_point], -cam.directions(xy)[on_point], atol=1e-6)
    # the two wider slivers are hit at their centroid, with the face normal +Z; the thinnest may be missed
    assert obj[-3] == 0 and obj[-2] == 1 and obj[-1] in (2, 4)
    np.testing.assert_allclose(normals[-3:-1], [[0, 0, 1], [0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(
        gbuf.primary.depth[-3:-1], np.linalg.norm(centroids[:2] - cam.position, axis=1), rtol=1e-6
    )


def test_coplanar_overlapping_triangles_shade_as_one_or_the_other_and_cast_no_shadow_on_each_other():
    red = quad("red", (-4, 0, 2), (8, 0, 0), (0, 0, -8), "red")
    blue = quad("blue", (-4, 0, 2), (8, 0, 0), (0, 0, -8), "blue")  # the same plane, the same triangles
    mats = {"red": Material(diffuse=(0.9, 0.1, 0.1)), "blue": Material(diffuse=(0.1, 0.1, 0.9))}
    light, intensity = np.array([0.5, 2.0, -1.0]), 4.0
    scene = Scene("coplanar", [red, blue], mats, [PointLight(position=tuple(light), intensity=(intensity,) * 3)])
    cam = camera(32, 32, HeadPose.looking((0.0, 1.0, 0.5), 0.0, -50.0))
    xy = pixel_centres(32, 32)
    rgb, gbuf, _ = trace_gbuffer(scene, cam, xy)
    again, gbuf2, _ = trace_gbuffer(scene, cam, xy)
    hit = gbuf.primary.object_id >= 0
    assert hit.sum() > 500 and set(np.unique(gbuf.primary.object_id[hit])) <= {0, 1}
    np.testing.assert_array_equal(rgb, again)  # the same choice every time
    np.testing.assert_array_equal(gbuf.primary.object_id, gbuf2.primary.object_id)
    assert np.all(gbuf.primary.shadow_count[hit] == 0)  # the coincident twin does not shadow the surface
    albedo = np.where((gbuf.primary.object_id[hit] == 0)[:, None], (0.9, 0.1, 0.1), (0.1, 0.1, 0.9))
    expected = lambert(cam, xy[hit], gbuf.primary.depth[hit], light, intensity, (0, 1, 0), (1, 1, 1)).T * albedo
    np.testing.assert_allclose(rgb[hit], expected, rtol=1e-4)


def test_rays_parallel_to_a_face_miss_it_or_hit_finitely():
    face = quad("q", (-1, 0, -1), (2, 0, 0), (0, 0, -2), "m")
    with Tracer(pack(Scene("t", [face], {"m": Material()})).geometry) as tracer:
        n = 200
        origins = np.zeros((n, 3), np.float32)
        origins[:, 0] = np.linspace(-1.5, 1.5, n)
        directions = np.tile(np.array([[0.0, 0.0, -1.0]], np.float32), (n, 1))  # in the face's plane
        for offset in (0.0, 1e-7, -1e-7):
            hits = tracer.intersect(origins + np.float32([0, offset, 0]), directions)
            assert np.all(np.isfinite(hits.t[hits.prim >= 0])) and np.all(np.isinf(hits.t[hits.prim < 0]))
            assert np.all(hits.t[hits.prim >= 0] <= 3.0 + 1e-5)
    cam = camera(32, 32, HeadPose.looking((0.0, 0.0, 1.0)))  # eye level with the face: the middle row grazes it
    rgb, gbuf, _ = trace_gbuffer(
        Scene("t", [face], {"m": Material()}, [PointLight(position=(0, 1, 0), intensity=(1, 1, 1))]),
        cam,
        pixel_centres(32, 32),
    )
    assert np.all(np.isfinite(rgb)) and np.all(np.isfinite(gbuf.primary.normal_shading))


@pytest.mark.parametrize("height", [1e-6, 1e6])
def test_hits_at_1e_minus_6_and_1e6_m_have_accurate_distances_and_closed_form_shading(height):
    """A camera `height` above a plane four times as wide, looking straight down, the light at twice the height."""
    half = 2.0 * height  # the view's footprint is +-1.07 height
    plane = quad("plane", (-half, 0, half), (2 * half, 0, 0), (0, 0, -2 * half), "m")
    light, intensity = np.array([0.3 * height, 2.0 * height, 0.0]), 3.0 * height * height
    scene = Scene(
        "plane",
        [plane],
        {"m": Material(diffuse=(0.5, 0.6, 0.7))},
        [PointLight(position=tuple(light), intensity=(intensity,) * 3)],
    )
    cam = camera(16, 16, HeadPose.looking((0.0, height, 0.0), 0.0, -90.0), centred=True)
    xy = pixel_centres(16, 16)
    rgb, gbuf, stats = trace_gbuffer(scene, cam, xy)
    dirs = cam.directions(xy).astype(np.float64)
    assert np.all(gbuf.primary.object_id == 0)
    np.testing.assert_allclose(gbuf.primary.depth, cam.position[1] / -dirs[:, 1], rtol=2e-6)
    assert np.all(gbuf.primary.shadow_count == 0) and stats.rays["shadow"] == 256  # no acne at either scale
    expected = lambert(cam, xy, gbuf.primary.depth, light, intensity, (0, 1, 0), (0.5, 0.6, 0.7)).T
    np.testing.assert_allclose(rgb, expected, rtol=1e-4)


def test_camera_inside_a_closed_mesh_sees_the_inside_lit_only_by_what_is_inside():
    mats = {"wall": Material(diffuse=(0.6, 0.5, 0.4))}
    room = box("room", (-1, -1, -1), (1, 1, 1), "wall")
    ambient = (0.2, 0.2, 0.2)
    outside = Scene("in", [room], mats, [PointLight(position=(0, 5, 0), intensity=(9, 9, 9))], ambient=ambient)
    cam = camera(16, 16, HeadPose.looking((0.1, 0.2, 0.3), 30.0, 10.0))
    xy = pixel_centres(16, 16)
    rgb, gbuf, _ = trace_gbuffer(outside, cam, xy)
    assert np.all(gbuf.primary.object_id == 0)  # every ray hits a wall from inside
    points = cam.position + gbuf.primary.depth[:, None] * cam.directions(xy).astype(np.float64)
    facing = np.einsum("ij,ij->i", np.array([0, 5, 0]) - points, gbuf.primary.normal_geometric) > 0
    assert facing.any() and np.all(gbuf.primary.shadow_count[facing] == 1)  # blocked wherever it could shine
    np.testing.assert_allclose(rgb, np.tile(np.multiply(ambient, (0.6, 0.5, 0.4)), (256, 1)), rtol=1e-6)
    light = np.array([0.0, 0.5, 0.0])
    inside = Scene("in", [room], mats, [PointLight(position=tuple(light), intensity=(2, 2, 2))])
    rgb, gbuf, _ = trace_gbuffer(inside, cam, xy)
    normals = gbuf.primary.normal_geometric.astype(np.float64)
    points = cam.position + gbuf.primary.depth[:, None] * cam.directions(xy).astype(np.float64)
    to_light = light - points
    r2 = np.einsum("ij,ij->i", to_light, to_light)
    cos = np.clip(np.einsum("ij,ij->i", to_light, normals) / np.sqrt(r2), 0, None)
    np.testing.assert_allclose(rgb, (2.0 * cos / r2)[:, None] * (0.6, 0.5, 0.4), rtol=1e-4, atol=1e-7)
    assert np.all(gbuf.primary.shadow_count == 0)


def glass_ball(max_depth: int) -> Scene:
    """A black, lossless glass sphere (all weight in Fresnel reflection and refraction) against a uniform sky."""
    mats = {"glass": Material(diffuse=(0.0, 0.0, 0.0), transmittance=1.0, ior=1.5)}
    ball = sphere("ball", (0.0, 0.0, -3.0), 1.0, "glass", subdivisions=5)
    return Scene("glass", [ball], mats, background=SKY, max_depth=max_depth)


def test_total_internal_reflection_at_grazing_angles_sends_everything_back():
    eta = 1.5  # glass to air
    critical = math.asin(1.0 / eta)
    for theta in (critical + 1e-9, 1.2, math.pi / 2 - 1e-9, math.pi / 2):
        cos_i = math.cos(theta)
        assert fresnel_dielectric(cos_i, eta) == 1.0
        assert split(0.0, 1.0, cos_i, eta) == (1.0, 0.0)  # all of it reflects
        ok, *_ = refract(math.sin(theta), 0.0, -cos_i, 0.0, 0.0, 1.0, eta)
        assert not ok
    for cos_i in (0.0, 1e-12):  # grazing from outside: total reflection in the limit, no NaN
        assert fresnel_dielectric(cos_i, 1.0 / eta) == pytest.approx(1.0, abs=1e-11)


def test_glass_sphere_at_grazing_angles_never_gains_energy():
    """Rays at impact parameters up to the silhouette, where the refracted ray meets the far side close to the
    critical angle (the tessellation's normals can tip it into total internal reflection); depth 16."""
    profile = msgspec.structs.replace(get_profile("sim-cpu").with_resolution(64, 64), ipd_mm=0.0)
    cam = EyeCamera.for_eye(profile, HeadPose())  # at the origin, the ball 3 m ahead
    ball = glass_ball(16)
    tri = ball.meshes[0].vertices[ball.meshes[0].faces] - (0.0, 0.0, -3.0)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inner = np.min(np.einsum("ij,ij->i", tri[:, 0], n / np.linalg.norm(n, axis=1, keepdims=True)))
    b = inner * np.concatenate([np.linspace(0.0, 0.99, 50), 1.0 - np.logspace(-2, -6, 50)])  # all inside the mesh
    tan = np.tan(np.arcsin(b / 3.0))
    xy = np.stack([(tan - cam.tan_left) / (cam.tan_right - cam.tan_left) * 64, np.full_like(b, 32.0)], axis=1)
    sky = np.array(SKY)
    rgb, gbuf, stats = trace_gbuffer(ball, cam, xy.astype(np.float32))
    assert np.all(gbuf.primary.object_id == 0) and stats.rays["secondary"] > 2 * len(b)
    assert np.all(np.isfinite(rgb)) and np.all(rgb <= sky * (1 + 1e-5))  # weights of a hit's children sum to 1
    np.testing.assert_allclose(rgb[:25], np.tile(sky, (25, 1)), rtol=1e-3)  # near normal incidence: all comes out
    assert np.all(rgb[50:] > 0.5 * sky)  # grazing: most is reflected straight off, none is lost to NaN


def test_recursion_depth_0_shows_only_local_shading_and_16_lets_the_sky_through():
    cam = camera(32, 32)
    xy = pixel_centres(32, 32)
    sky = np.array(SKY)
    rgb0, gbuf0, stats0 = trace_gbuffer(glass_ball(0), cam, xy)
    on_ball = gbuf0.primary.object_id == 0
    assert on_ball.sum() > 50 and stats0.rays["secondary"] == 0
    np.testing.assert_array_equal(rgb0[on_ball], 0.0)  # black glass without bounces
    np.testing.assert_allclose(rgb0[~on_ball], np.tile(sky, ((~on_ball).sum(), 1)), rtol=1e-6)
    rgb16, _, stats16 = trace_gbuffer(glass_ball(16), cam, xy)
    assert stats16.rays["secondary"] > 0 and np.all(np.isfinite(rgb16))
    assert np.all(rgb16 <= sky * (1 + 1e-5))
    centre = np.linalg.norm(xy - 16.0, axis=1) < 4.0  # near-normal incidence: little stays trapped
    np.testing.assert_allclose(rgb16[centre], np.tile(sky, (centre.sum(), 1)), rtol=1e-3)
    with pytest.raises(SceneError, match="outside"):
        load_scene("whitted?max_depth=17")


# ---------------------------------------------------------------------------------------------------------------
# stiff dynamics: head-pose fusion, gaze and pose prediction, fixation smoothing, clock sync
# ---------------------------------------------------------------------------------------------------------------

LEVEL = (0.0, GRAVITY, 0.0)


def levelled(gain: float = 1.0, **kw) -> OrientationFusion:
    fusion = OrientationFusion(gain=gain, **kw)
    fusion.update((0.0, 0.0, 0.0), LEVEL, 0)  # the first usable sample aligns the tilt
    assert fusion.orientation == (1.0, 0.0, 0.0, 0.0)
    return fusion


def tilt_error_deg(q, up) -> float:
    """Angle between the up direction the estimate predicts (R^T +Y) and the measured one."""
    w, x, y, z = q
    v = np.array([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)])
    u = np.asarray(up) / np.linalg.norm(up)
    return math.degrees(math.atan2(np.linalg.norm(np.cross(v, u)), float(v @ u)))


def test_fusion_with_dt_0_or_negative_changes_nothing():
    fusion = levelled()
    before = fusion.orientation
    for dt in (0, -1, -(10**9)):
        assert fusion.update((5.0, -3.0, 2.0), (1.0, GRAVITY, 0.0), dt) == before
    assert fusion.clamped == 0 and fusion.gain_limited == 0


def test_fusion_after_a_1_s_stall_clamps_the_step_to_max_dt_and_counts_it():
    fusion = levelled(gain=0.0, max_dt_ns=100 * MS)
    rate = math.radians(90.0)
    q = fusion.update((0.0, rate, 0.0), LEVEL, 1_000 * MS)
    half = 0.5 * rate * 0.1  # 0.1 s of rotation, not 1 s
    np.testing.assert_allclose(q, (math.cos(half), 0.0, math.sin(half), 0.0), atol=1e-15)
    assert fusion.clamped == 1


@pytest.mark.parametrize("gain_dt", [0.5, 1.0, 2.0, 2.5, 10.0, 1e6])
def test_fusion_gain_at_and_beyond_the_explicit_stability_limit_is_limited_to_one_step_and_counted(gain_dt):
    """The tilt correction turns by gain dt times the error per step: it would overshoot past gain dt = 1 and
    diverge past 2. Each step uses min(gain, 1 / dt), counted in gain_limited."""
    dt_ns = 10 * MS
    fusion = levelled(gain=gain_dt / 0.01, max_dt_ns=dt_ns)
    tilt = math.radians(20.0)
    up = (0.0, GRAVITY * math.cos(tilt), -GRAVITY * math.sin(tilt))
    errors = [tilt_error_deg(fusion.update((0.0, 0.0, 0.0), up, dt_ns), up) for _ in range(60)]
    effective = min(gain_dt, 1.0)
    # one step turns by effective * sin(error): 20 deg -> 20 - degrees(effective sin 20 deg)
    assert errors[0] == pytest.approx(20.0 - math.degrees(effective * math.sin(tilt)), abs=1e-9)
    assert all(b <= a + 1e-12 for a, b in zip(errors, errors[1:], strict=False))  # never overshoots
    assert errors[-1] < 1e-9
    assert fusion.gain_limited == (60 if gain_dt > 1.0 else 0)


def test_fusion_at_2000_deg_per_s_integrates_the_rotation_exactly():
    for gain in (0.0, 1.0):  # a level head turning about the vertical: the tilt correction has nothing to do
        fusion = levelled(gain=gain)
        rate = math.radians(2000.0)
        for _ in range(1000):
            q = fusion.update((0.0, rate, 0.0), LEVEL, MS)
        half = math.radians(2000.0) / 2  # 2000 degrees in 1 s
        np.testing.assert_allclose(np.abs(q), np.abs((math.cos(half), 0.0, math.sin(half), 0.0)), atol=1e-11)
        assert math.copysign(1, q[0] * q[2]) == math.copysign(1, math.cos(half) * math.sin(half))


def check_quaternion_norm_drift(updates: int, angle_tol: float) -> None:
    """gain 0, a constant body rate about a fixed tilted axis at 1 kHz: the closed form is one rotation."""
    fusion = levelled(gain=0.0)
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    omega = math.radians(2000.0) * axis
    gyro = tuple(omega)
    update = fusion.update
    for _ in range(updates):
        q = update(gyro, LEVEL, MS)
    assert abs(math.sqrt(sum(c * c for c in q)) - 1.0) < 1e-14
    angle = math.radians(2000.0) * updates * 1e-3
    exact = np.concatenate([[math.cos(angle / 2)], axis * math.sin(angle / 2)])
    assert min(np.linalg.norm(np.subtract(q, exact)), np.linalg.norm(np.add(q, exact))) < angle_tol


def test_fusion_quaternion_norm_does_not_drift_over_100_thousand_updates():
    check_quaternion_norm_drift(100_000, 1e-11)


def test_fusion_rejects_and_counts_non_finite_samples():
    fusion = levelled()
    before = fusion.orientation
    for gyro, accel in (((math.nan, 0, 0), LEVEL), ((0, 0, 0), (math.inf, 0, 0)), ((1e308, 1e308, 0), LEVEL)):
        assert fusion.update(gyro, accel, MS) == before
    assert fusion.rejected == 3


def gaze(seq: int, t_ns: int, yaw: float = 0.0, valid: bool = True) -> Gaze:
    return Gaze(seq=seq, t_host=t_ns, valid=valid, C=tuple(gaze_direction(yaw, 0.0)) if valid else None)


def yaw_of(v) -> float:
    return math.degrees(math.atan2(v[0], -v[2]))


def test_gaze_samples_with_dt_0_between_them_give_no_velocity_and_no_division_by_zero():
    store = SampleStore()
    assert store.add("eye", gaze(0, 0, 0.0), 0) and store.add("eye", gaze(1, 0, 10.0), 0)  # same capture time
    est = store.gaze_at(5 * MS, now_ns=5 * MS)
    assert est.source_seq == 1 and yaw_of(est.left) == pytest.approx(10.0) and est.speed_deg_s == 0.0
    pose_store = SampleStore()
    for seq, yaw in ((0, 0.0), (1, 40.0)):
        q = tuple(quat_from_yaw_pitch(yaw, 0.0))
        assert pose_store.add("head", Pose(seq=seq, t_host=0, position=(0, 0, 0), orientation=q), 0)
    p = pose_store.pose_at(5 * MS, now_ns=5 * MS)
    assert np.all(np.isfinite(p.orientation)) and abs(np.linalg.norm(p.orientation) - 1) < 1e-12


def test_gaze_prediction_after_a_1_s_stall_stops_at_the_horizon_and_forgets_the_old_velocity():
    store = SampleStore(horizon_ns=50 * MS)
    for i in range(11):
        store.add("eye", gaze(i, i * MS, 0.1 * i), i * MS)  # 100 deg/s
    stalled = store.gaze_at(1010 * MS, now_ns=1000 * MS)
    assert stalled.clamped and stalled.predicted_ns == 50 * MS and stalled.age_ns == 1000 * MS
    assert yaw_of(stalled.left) == pytest.approx(1.0 + 100.0 * 0.050, abs=1e-9)  # the horizon, not 1 s of motion
    store.add("eye", gaze(11, 1000 * MS, 5.0), 1000 * MS)
    after = store.gaze_at(1010 * MS, now_ns=1000 * MS)
    assert after.speed_deg_s == 0.0 and yaw_of(after.left) == pytest.approx(5.0)  # no velocity across the stall
    across = store.gaze_at(505 * MS, now_ns=1000 * MS)  # halfway through the gap: interpolated, finite
    assert yaw_of(across.left) == pytest.approx(3.0, abs=1e-9)


def test_gaze_and_pose_at_2000_deg_per_s_are_predicted_and_interpolated_on_the_closed_form():
    store = SampleStore()
    for i in range(11):  # 2 degrees per 1 ms sample
        store.add("eye", gaze(i, i * MS, 2.0 * i), i * MS)
        q = tuple(quat_from_yaw_pitch(2.0 * i, 0.0))
        store.add("head", Pose(seq=i, t_host=i * MS, position=(0, 0, 0), orientation=q), i * MS)
    est = store.gaze_at(30 * MS, now_ns=10 * MS)
    assert yaw_of(est.left) == pytest.approx(60.0, abs=1e-9) and est.speed_deg_s == pytest.approx(2000.0)
    assert yaw_of(store.gaze_at(round(4.5 * MS), now_ns=10 * MS).left) == pytest.approx(9.0, abs=1e-9)
    pose = store.pose_at(30 * MS, now_ns=10 * MS)
    expected = quat_from_yaw_pitch(60.0, 0.0)
    assert min(np.linalg.norm(pose.orientation - expected), np.linalg.norm(pose.orientation + expected)) < 1e-12
    far = store.gaze_at(80 * MS, now_ns=10 * MS)  # 70 ms ahead: stops at the 50 ms horizon, flagged
    assert far.clamped and yaw_of(far.left) == pytest.approx(120.0, abs=1e-9)


def test_fixation_filter_alpha_1_passes_the_gaze_and_alpha_beyond_1_or_0_is_refused():
    """The EMA s <- s + alpha (g - s) is stable for 0 < alpha < 2 but overshoots above 1: the filter refuses
    alpha outside (0, 1]; alpha = 1 is the unfiltered gaze."""
    for alpha in (0.0, -0.5, 1.0 + 1e-12, 2.0, math.nan):
        with pytest.raises(ValueError, match="alpha"):
            FixationFilter(alpha)
    filt = FixationFilter(1.0, saccade_deg=3.0)
    for yaw in (0.0, 1.0, 2.5, 2.0):
        np.testing.assert_allclose(filt(gaze_direction(yaw, 0.0)), gaze_direction(yaw, 0.0), atol=1e-15)


def test_fixation_filter_counts_samples_not_time_so_a_stall_is_one_step():
    filt = FixationFilter(0.25, saccade_deg=3.0)
    filt(gaze_direction(0.0, 0.0))
    state = filt(gaze_direction(2.0, 0.0))  # after a 1 s stall or 1 ms: the same single step
    blend = 0.25 * gaze_direction(2.0, 0.0) + 0.75 * gaze_direction(0.0, 0.0)
    np.testing.assert_allclose(state, blend / np.linalg.norm(blend), atol=1e-15)
    for _ in range(3):  # the same sample again (dt = 0 duplicates): converges, stays unit
        state = filt(gaze_direction(2.0, 0.0))
    assert abs(np.linalg.norm(state) - 1) < 1e-15 and 0.0 < yaw_of(state) < 2.0


def test_fixation_filter_with_nan_gaze_is_an_error_and_keeps_its_state():
    filt = FixationFilter(0.5)
    state = filt(gaze_direction(1.0, 0.0)).copy()
    for bad in ((math.nan, 0.0, -1.0), (math.inf, 0.0, 0.0), (0.0, 0.0, 0.0)):
        with pytest.raises(ValueError, match="finite"):
            filt(np.array(bad))
    np.testing.assert_array_equal(filt.state, state)


def test_fixation_filter_opposite_gaze_with_a_180_degree_saccade_threshold_jumps_instead_of_nan():
    filt = FixationFilter(0.5, saccade_deg=180.0)
    filt(np.array([0.0, 0.0, -1.0]))
    np.testing.assert_array_equal(filt(np.array([0.0, 0.0, 1.0])), [0.0, 0.0, 1.0])  # the blend cancels out


def test_clock_sync_with_one_sample_maps_by_its_offset_with_no_drift():
    sync = ClockSync(floor_ns=2 * MS)
    assert sync.add(1_000, 5_000_000_000) == 5_000_000_000 - 2 * MS  # capture = receive - known latency
    est = sync.estimate()
    assert est.pairs == 1 and est.drift_ppm == 0.0 and est.offset_ns == 5_000_000_000 - 1_000 - 2 * MS
    assert sync.to_host(1_000 + 7 * MS) == 5_000_000_000 - 2 * MS + 7 * MS


def test_clock_sync_with_zero_variance_latency_fits_the_exact_offset_and_no_drift():
    sync = ClockSync(floor_ns=3 * MS)
    base = 42_000_000_000
    captures = [sync.add(i * 4 * MS, base + i * 4 * MS + 3 * MS) for i in range(2_500)]  # 10 s at 250 Hz
    assert captures == [base + i * 4 * MS for i in range(2_500)]
    est = sync.estimate()
    assert est.drift_ppm == 0.0 and est.residual_ns == 0.0 and est.offset_ns == pytest.approx(base, abs=0.5)


def test_clock_sync_across_a_1_s_stall_maps_capture_times_exactly():
    """Samples stop for 1 s, then the host receives a burst 1 s late (a stalled reader) before catching up: no
    reset (the jump is within reset_ns), and every sample still maps to its true capture time."""
    latency = MS
    sync = ClockSync(floor_ns=latency)
    base = 5_000_000_000
    for i in range(3_000):  # 3 s at 1 kHz
        if 1_000 <= i < 2_000:
            continue  # the device sent nothing for 1 s
        t_dev = i * MS
        delay = 1_000 * MS if 2_000 <= i < 2_100 else 0  # the first 100 ms after it arrive 1 s late
        assert sync.add(t_dev, base + t_dev + latency + delay) == base + t_dev
    est = sync.estimate()
    assert sync.resets == 0 and est.drift_ppm == 0.0 and est.offset_ns == pytest.approx(base, abs=0.5)


def test_clock_sync_with_a_frozen_device_clock_stays_finite_with_no_slope():
    sync = ClockSync(window_ns=1, min_span_ns=0)
    out = [sync.add(5_000, 1_000_000 + k) for k in range(50)]  # the device repeats one timestamp
    assert out == [1_000_000] * 50 and sync.estimate().drift_ppm == 0.0
    # a device clock stepping back to one time after every late sample: each window's minimum sits at t_dev = 0,
    # so the minima span no device time and the least-squares slope would be 0 / 0
    sync = ClockSync(window_ns=1, min_span_ns=0)
    for k in range(40):
        if k % 2:
            sync.add((k + 1) // 2, 15_000 + 10 * k)  # late
        else:
            sync.add(0, 10_000 + 10 * k)
    est = sync.estimate()
    assert est.offset_ns == 10_000.0 and est.drift_ppm == 0.0 and sync.to_host(0) == 10_000  # the lowest minimum


def test_clock_sync_with_a_zero_or_negative_window_is_an_error():
    for kwargs in ({"window_ns": 0}, {"windows": 0}, {"reset_ns": 0}, {"min_span_ns": -1}, {"wrap_ns": 0}):
        with pytest.raises(ValueError, match="clock sync needs"):
            ClockSync(**kwargs)


def test_device_clock_jumps_of_plus_and_minus_10_s_reset_the_sync_and_are_counted():
    latency = 2 * MS
    sync = ClockSync(floor_ns=latency)
    host = 100_000_000_000
    jump = 0
    for i in range(3_000):  # 1 kHz for 3 s; the device clock jumps +10 s at 1 s and -10 s at 2 s
        if i == 1_000:
            jump = 10_000_000_000
        elif i == 2_000:
            jump = 0
        capture = host + i * MS
        assert sync.add(7 * MS + i * MS + jump, capture + latency) == capture
    assert sync.resets == 2


def test_sample_store_drops_gaze_whose_host_time_jumps_10_s_and_counts_it():
    store = SampleStore()
    for i in range(11):
        store.add("eye", gaze(i, i * MS), i * MS)
    assert not store.add("eye", gaze(11, 11 * MS + 10_000 * MS, 30.0), 11 * MS)  # 10 s ahead of its arrival
    assert not store.add("eye", gaze(12, 12 * MS - 10_000 * MS, 30.0), 12 * MS)  # 10 s behind the newest
    counts = store.counts()["eye"]
    assert (counts.ahead, counts.too_old, counts.dropped, counts.stored) == (1, 1, 2, 11)
    assert yaw_of(store.gaze_at(12 * MS, 12 * MS).left) == pytest.approx(0.0)


# ---------------------------------------------------------------------------------------------------------------
# inputs: bad gaze, blinks, disorder, rates, sizes, empty scenes
# ---------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_or_infinite_gaze_is_dropped_and_counted_by_the_store_and_refused_by_the_renderer(bad):
    store = SampleStore()
    store.add("eye", gaze(0, 0, 3.0), 0)
    for seq, fields in enumerate(({"C": (bad, 0.0, -1.0)}, {"L": (0.0, bad, -1.0)}, {"R": (0.0, 0.0, bad)}), 1):
        assert not store.add("eye", Gaze(seq=seq, t_host=seq * MS, **fields), seq * MS)
    assert not store.add("eye", Gaze(seq=9, t_host=9 * MS, C=(0.0, 0.0, -1.0), depth_m=bad), 9 * MS)
    counts = store.counts()["eye"]
    assert counts.malformed == 4 and counts.stored == 1
    assert yaw_of(store.gaze_at(10 * MS, 10 * MS).left) == pytest.approx(3.0)
    cam = camera(8, 8)
    with pytest.raises(ValueError, match="finite"):
        FrameRequest(cam, np.array([bad, 0.0, -1.0]))
    with pytest.raises(ValueError, match="finite"):
        cam.gaze_pixel(np.array([0.0, bad, -1.0]))
    with pytest.raises(ConfigError, match="finite"):
        parse_gaze(f"{bad},0")


def test_a_half_second_blink_holds_the_last_gaze_and_a_half_second_gap_stops_prediction_at_the_horizon():
    store = SampleStore(horizon_ns=50 * MS)
    for i in range(101):
        store.add("eye", gaze(i, i * MS, 0.05 * i), i * MS)  # 50 deg/s up to 100 ms
    for i in range(101, 601):
        store.add("eye", gaze(i, i * MS, valid=False), i * MS)  # eyes closed for 0.5 s
    during = store.gaze_at(400 * MS, now_ns=400 * MS)
    assert during.blinking and during.blink_since_ns == 101 * MS and during.predicted_ns == 0
    assert yaw_of(during.left) == pytest.approx(5.0, abs=1e-9)  # held, not extrapolated 0.3 s at 50 deg/s
    for i in range(601, 611):
        store.add("eye", gaze(i, i * MS, 8.0), i * MS)
    after = store.gaze_at(620 * MS, now_ns=610 * MS)
    assert not after.blinking and after.speed_deg_s == 0.0 and yaw_of(after.left) == pytest.approx(8.0)
    gap = store.gaze_at(1110 * MS, now_ns=1110 * MS)  # no samples at all for 0.5 s
    assert gap.clamped and gap.predicted_ns == 50 * MS and yaw_of(gap.left) == pytest.approx(8.0)
    assert store.counts()["eye"].invalid == 500


def test_gaze_out_of_order_and_duplicated_gives_the_same_estimates_as_in_order_and_is_counted():
    rng = np.random.default_rng(4)
    samples = [gaze(i, i * MS, 20.0 * math.sin(i / 40.0)) for i in range(200)]
    received = {s.seq: (s.seq // 10 + 1) * 10 * MS for s in samples}  # bursts of 10, delivered at the burst's end
    ordered, shuffled = SampleStore(), SampleStore()
    for s in samples:
        ordered.add("eye", s, received[s.seq])
    arrivals = []
    for burst in range(20):
        chunk = samples[burst * 10 : burst * 10 + 10]
        arrivals += [chunk[i] for i in rng.permutation(10)]
    duplicates = [samples[i] for i in rng.choice(200, 25, replace=False)]
    for s in arrivals + duplicates:
        shuffled.add("eye", s, received[s.seq])
    counts = shuffled.counts()["eye"]
    assert counts.duplicates == 25 and counts.out_of_order > 0 and counts.stored == 200
    for t, now in ((5 * MS, 10 * MS), (55 * MS, 60 * MS), (125 * MS, 130 * MS), (230 * MS, 200 * MS)):
        a, b = ordered.gaze_at(t, now), shuffled.gaze_at(t, now)
        np.testing.assert_array_equal(a.left, b.left)
        assert (a.source_seq, a.predicted_ns) == (b.source_seq, b.predicted_ns)


def test_1_khz_gaze_into_a_60_hz_compositor_tracks_the_closed_form_within_the_prediction_error():
    """A sinusoidal saccade-free gaze (yaw = 10 sin(2 pi 2 t)) at 1 kHz, 2 ms transport latency; each 60 Hz frame
    asks for the gaze 20 ms ahead, h <= 23 ms past the newest sample that has arrived. The velocity fitted over
    3 samples 1 ms apart is the slope 0.9 ms back, so the error is at most |yaw''| (h^2 / 2 + 0.9 ms h) = 0.45 deg."""

    def yaw_at(t_ns: int) -> float:
        return 10.0 * math.sin(2 * math.pi * 2.0 * t_ns * 1e-9)

    store = SampleStore()
    for i in range(1001):
        store.add("eye", gaze(i, i * MS, yaw_at(i * MS)), i * MS + 2 * MS)
    errors = []
    for frame in range(1, 60):
        now = round(frame * 1e9 / 60)
        est = store.gaze_at(now + 20 * MS, now)
        assert est.source_t_host <= now - 2 * MS  # only samples that had arrived
        errors.append(abs(yaw_of(est.left) - yaw_at(now + 20 * MS)))
    h = 0.023
    assert max(errors) <= 10.0 * (4 * math.pi) ** 2 * (h * h / 2 + 0.0009 * h)
    assert max(errors) > 0.3  # the bound is close: it is a prediction, not a lookup of the future
    counts = store.counts()["eye"]
    assert counts.samples == 1001 and counts.dropped == 0


def test_zero_size_profiles_are_an_error(tmp_path):
    profile = get_profile("sim-cpu")
    for w, h in ((0, 16), (16, 0), (0, 0), (-1, 4)):
        with pytest.raises(ConfigError, match="at least 1x1"):
            profile.with_resolution(w, h)
    with pytest.raises(ConfigError, match="at least 1x1"):
        profile.with_resolution_text("0x720")
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert(
            {
                "name": "z",
                "width": 0,
                "height": 1,
                "fov": {"left": -40, "right": 40, "up": 40, "down": -40},
                "refresh_hz": 60,
            },
            HmdProfile,
        )
    path = tmp_path / "zero.toml"
    fov = "[fov]\nleft = -40.0\nright = 40.0\nup = 40.0\ndown = -40.0\n"
    path.write_text(f'name = "z"\nwidth = 0\nheight = 10\nrefresh_hz = 60.0\n{fov}')
    with pytest.raises(ConfigError, match="width"):
        get_profile(str(path))


def test_a_1x1_profile_renders_the_centre_ray_finitely_with_every_method():
    scene = load_scene("whitted")
    reference, _ = render_frames(scene, "full", [FORWARD], 1, 1)
    for method in METHODS:
        images, _ = render_frames(scene, method, [FORWARD] * 3, 1, 1)
        for im in images:
            assert im.shape == (1, 1, 3) and np.all(np.isfinite(im)) and np.all(im >= 0), method
        if method != "regular":  # regular averages 36 jittered samples over the whole (90 degree) pixel
            np.testing.assert_allclose(images[-1], reference[0], rtol=1e-5, atol=1e-6, err_msg=method)


def test_an_empty_scene_renders_the_background_with_every_method():
    gazes = [FORWARD, gaze_direction(10.0, 5.0)] * 6  # 12 frames: one refresh cycle of rrm's persistent buffer
    for method in METHODS:
        images, stats = render_frames(empty_scene(), method, gazes)
        for im in images if method != "rrm" else images[-1:]:
            np.testing.assert_allclose(im, np.broadcast_to(SKY, im.shape), rtol=1e-6, err_msg=method)
        assert stats[-1].rays["shadow"] == 0 and stats[-1].rays["secondary"] == 0
