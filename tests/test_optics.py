"""Profiles, per-eye cameras and eccentricity maps."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hmdrt.errors import ConfigError
from hmdrt.optics import PROFILES, EyeCamera, Fov, get_profile
from hmdrt.spatial import Pose, gaze_direction, quat_to_matrix


def camera(profile: str, yaw=0.0, pitch=0.0, eye="left", position=(0.0, 1.6, 0.0)) -> EyeCamera:
    return EyeCamera.for_eye(get_profile(profile), Pose.looking(position, yaw, pitch), eye)


@settings(max_examples=60, deadline=None)
@given(
    profile=st.sampled_from(sorted(PROFILES)),
    eye=st.sampled_from(["left", "right"]),
    yaw=st.floats(-180, 180),
    pitch=st.floats(-80, 80),
    fx=st.floats(0.0, 1.0),
    fy=st.floats(0.0, 1.0),
)
def test_pixel_ray_pixel_round_trip(profile, eye, yaw, pitch, fx, fy):
    cam = camera(profile, yaw, pitch, eye)
    xy = np.array([[fx * cam.width, fy * cam.height]], dtype=np.float32)
    d = cam.directions(xy)
    assert abs(np.linalg.norm(d[0]) - 1.0) < 1e-6
    back, depth = cam.project(cam.position + 3.0 * d.astype(np.float64))
    assert depth[0] > 0
    np.testing.assert_allclose(back, xy, atol=2e-3)


def test_centre_ray_looks_down_minus_z_of_the_head():
    cam = camera("rift_s", yaw=30.0, pitch=-10.0)
    centre = cam.directions(np.array([[cam.width / 2, cam.height / 2]], np.float32))[0]
    forward = quat_to_matrix(Pose.looking((0, 0, 0), 30.0, -10.0).orientation) @ [0, 0, -1]
    np.testing.assert_allclose(centre, forward, atol=1e-6)
    assert forward[0] > 0 and forward[1] < 0  # right and down


def test_eyes_are_one_ipd_apart():
    p = get_profile("dk2")
    left, right = camera("dk2", eye="left"), camera("dk2", eye="right")
    assert math.isclose(np.linalg.norm(right.position - left.position), p.ipd_mm * 1e-3, rel_tol=1e-9)
    assert right.position[0] > left.position[0]


@pytest.mark.parametrize("profile", sorted(PROFILES))
def test_eccentricity_is_zero_at_the_gaze_pixel(profile):
    cam = camera(profile)
    gaze = gaze_direction(12.0, -7.0)
    px = cam.gaze_pixel(gaze)
    assert cam.eccentricity(gaze, px[None].astype(np.float32))[0] < 2e-3


@pytest.mark.parametrize("profile", sorted(PROFILES))
def test_eccentricity_at_the_frustum_edges_equals_the_half_fov(profile):
    p = get_profile(profile)
    cam = camera(profile)
    forward = np.array([0.0, 0.0, -1.0])
    row = cam.gaze_pixel(forward)[1]  # the row where the view ray is level with the gaze
    col = cam.gaze_pixel(forward)[0]
    edges = np.array([[0.0, row], [cam.width, row], [col, 0.0], [col, cam.height]], dtype=np.float32)
    ecc = cam.eccentricity(forward, edges)
    np.testing.assert_allclose(ecc, [-p.fov.left, p.fov.right, p.fov.up, -p.fov.down], atol=2e-3)


def test_eccentricity_is_an_angle_not_a_pixel_distance():
    cam = camera("vive_pro_eye")
    ecc = cam.eccentricity(np.array([0.0, 0.0, -1.0]))
    assert ecc.shape == (cam.height, cam.width)
    xy = np.array([[0.5, 0.5], [cam.width - 0.5, cam.height - 0.5]], np.float32)
    d = cam.directions(xy)
    expected = np.degrees(np.arccos(-d[:, 2]))  # the head is unrotated, so the eye frame is the world frame
    np.testing.assert_allclose(cam.eccentricity(np.array([0.0, 0.0, -1.0]), xy), expected, atol=1e-3)
    # equal pixel steps from the centre give shrinking angle steps towards the edge
    col, row = (int(c) for c in cam.gaze_pixel(np.array([0.0, 0.0, -1.0])))
    steps = np.diff(ecc[row, col:])
    assert steps[0] > steps[-1] > 0


def test_asymmetric_frustum_mirrors_between_eyes():
    left, right = get_profile("dk2").eye_fov("left"), get_profile("dk2").eye_fov("right")
    assert left.left == -right.right and left.right == -right.left and left.up == right.up


@pytest.mark.parametrize("w,h", [(0, 10), (10, 0), (-1, 5)])
def test_zero_resolution_is_refused(w, h):
    with pytest.raises(ConfigError, match="at least 1x1"):
        get_profile("rift_s").with_resolution(w, h)


def test_profile_from_toml(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text(
        'name = "mine"\nwidth = 100\nheight = 80\nrefresh_hz = 120.0\n'
        "fov = { left = -40.0, right = 50.0, up = 45.0, down = -45.0 }\n"
    )
    p = get_profile(str(f))
    assert (p.width, p.height, p.refresh_hz) == (100, 80, 120.0)
    assert p.period_ns == 8333333
    f.write_text(
        'name = "bad"\nwidth = 0\nheight = 80\nrefresh_hz = 120.0\n'
        "fov = { left = -40.0, right = 50.0, up = 45.0, down = -45.0 }\n"
    )
    with pytest.raises(ConfigError, match="width"):
        get_profile(str(f))


def test_fov_must_be_ordered():
    import msgspec

    with pytest.raises(msgspec.ValidationError):
        msgspec.convert({"left": 10.0, "right": -10.0, "up": 5.0, "down": -5.0}, Fov)
