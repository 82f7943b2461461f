"""Numerical stability at the edges: kim2021's tau_fov Bezier segments and the temporal smoothing weights."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest

from hmdrt.errors import ConfigError
from hmdrt.foveation import MethodChoice
from hmdrt.foveation.kim21 import Kim21Params, bezier_controls, tau_fov_array
from hmdrt.foveation.stages.temporal import History, exponential_smoothing
from hmdrt.optics import EyeCamera
from hmdrt.scene import load_scene
from tests.stability.common import (
    FORWARD,
    camera,
    render_frames,
)


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
