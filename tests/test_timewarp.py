"""Rotational timewarp: identity, one-pixel turns, agreement with EyeCamera.project, edge handling and
the outside fraction, on symmetric (sim-cpu) and asymmetric (dk2, vive_pro_eye) frusta of both eyes."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest

from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.profiles import HmdProfile
from hmdrt.present.timewarp import Warp, _warp, homography, timewarp
from hmdrt.spatial import Pose, quat_from_yaw_pitch, quat_multiply

HEAD = np.array([0.2, 1.6, -0.4])
EYES = ("left", "right")


def small(name: str) -> HmdProfile:
    """The profile's optics at about sim-cpu's pixel count, to keep the tests fast."""
    profile = get_profile(name)
    return profile if name == "sim-cpu" else profile.with_resolution(160, 192)


def camera(profile: HmdProfile, eye: str, yaw: float = 0.0, pitch: float = 0.0, roll: float = 0.0) -> EyeCamera:
    half = math.radians(roll) / 2
    q = quat_multiply(quat_from_yaw_pitch(yaw, pitch), np.array([math.cos(half), 0.0, 0.0, math.sin(half)]))
    return EyeCamera.for_eye(profile, Pose(HEAD, q), eye)


def texture(profile: HmdProfile, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).random((profile.height, profile.width, 3), dtype=np.float32)


def principal_pixel(cam: EyeCamera) -> tuple[int, int]:
    """The pixel (column, row) the camera's optical axis passes through."""
    xy = cam.project((cam.position + cam.rotation @ [0.0, 0.0, -1.0])[None])[0][0]
    return int(xy[0]), int(xy[1])


def reference_outside(rendered: EyeCamera, target: EyeCamera) -> float:
    """Fraction of target pixel centres whose direction misses the rendered image, via EyeCamera's own methods."""
    ys, xs = np.mgrid[0 : target.height, 0 : target.width] + 0.5
    dirs = target.directions(np.stack([xs.ravel(), ys.ravel()], axis=1))
    xy, depth = rendered.project(rendered.position + dirs.astype(np.float64))
    with np.errstate(invalid="ignore"):
        inside = (depth > 0) & (xy[:, 0] >= 0) & (xy[:, 0] < rendered.width) & (xy[:, 1] >= 0)
        inside &= xy[:, 1] < rendered.height
    return 1.0 - inside.mean()


PROFILES_EYES = [(name, eye) for name in ("sim-cpu", "dk2", "vive_pro_eye") for eye in EYES]


@pytest.mark.parametrize(("name", "eye"), PROFILES_EYES)
def test_identity_returns_the_image(name: str, eye: str) -> None:
    profile = small(name)
    image = texture(profile)
    rendered = camera(profile, eye, 7.0, -3.0, 2.0)
    moved = EyeCamera(**{**rendered.__dict__, "position": rendered.position + [0.3, -0.1, 0.5]})
    for target in (rendered, moved):  # positions are ignored: only the rotation matters
        warped, outside = timewarp(image, rendered, target)
        # the homography's float64 rounding vanishes in float32 lookups: they land on pixel centres, blended
        # with weights of exactly 0
        np.testing.assert_array_equal(warped, image)
        assert outside == 0.0


@pytest.mark.parametrize(("name", "eye"), [("sim-cpu", "left"), ("dk2", "left"), ("dk2", "right")])
def test_yaw_of_one_pixel_shifts_by_one_pixel(name: str, eye: str) -> None:
    profile = small(name)
    rendered = camera(profile, eye)
    pixel_deg = math.degrees(math.atan((rendered.tan_right - rendered.tan_left) / rendered.width))
    target = camera(profile, eye, yaw=pixel_deg)  # a right turn: the scene moves one pixel left
    image = texture(profile)
    warped = timewarp(image, rendered, target).image
    cx, cy = principal_pixel(rendered)
    rows, cols = slice(cy - 8, cy + 8), slice(cx - 8, cx + 8)
    shifted = image[rows, cx - 7 : cx + 9]
    assert np.abs(warped[rows, cols] - shifted).max() < 0.03
    assert np.abs(warped[rows, cols] - image[rows, cols]).mean() > 0.2


@pytest.mark.parametrize(("name", "eye"), PROFILES_EYES)
def test_marked_pixel_lands_where_eyecamera_projects_it(name: str, eye: str) -> None:
    profile = small(name)
    rendered = camera(profile, eye, 10.0, 5.0)
    target = camera(profile, eye, 14.0, 2.0, 3.0)
    col, row = int(0.3 * profile.width), int(0.6 * profile.height)
    image = np.zeros((profile.height, profile.width, 3), np.float32)
    image[row, col] = 1.0
    direction = rendered.directions(np.array([[col + 0.5, row + 0.5]]))[0].astype(np.float64)
    expected = target.project((target.position + direction)[None])[0][0]
    expected_in_target = expected - [col + 0.5, row + 0.5]
    assert np.hypot(*expected_in_target) > 5.0  # the rotation does move the mark

    lum = timewarp(image, rendered, target).image[..., 0]
    ys, xs = np.mgrid[0 : profile.height, 0 : profile.width] + 0.5
    centroid = np.array([(xs * lum).sum(), (ys * lum).sum()]) / lum.sum()
    assert np.hypot(*(centroid - expected)) < 0.5
    peak_row, peak_col = np.unravel_index(np.argmax(lum), lum.shape)
    assert abs(peak_col + 0.5 - expected[0]) <= 1.0 and abs(peak_row + 0.5 - expected[1]) <= 1.0


@pytest.mark.parametrize(("name", "eye"), [("sim-cpu", "left"), ("dk2", "right"), ("vive_pro_eye", "left")])
def test_outside_fraction_grows_with_rotation_and_matches_eyecamera(name: str, eye: str) -> None:
    profile = small(name)
    image = texture(profile)
    rendered = camera(profile, eye)
    fractions = []
    for yaw in (0.0, 0.5, 2.0, 8.0, 20.0):
        target = camera(profile, eye, yaw, yaw / 2)
        outside = timewarp(image, rendered, target).outside
        assert outside == pytest.approx(reference_outside(rendered, target), abs=2.0 / image[..., 0].size)
        fractions.append(outside)
    assert fractions[0] == 0.0
    assert all(a < b for a, b in zip(fractions, fractions[1:], strict=False))


def test_uncovered_pixels_repeat_the_edge_and_behind_the_eye_is_black() -> None:
    profile = small("sim-cpu")
    image = texture(profile)
    image[:, -1] = 0.7  # the right edge column: what a right turn must repeat
    rendered = camera(profile, "left")
    warped, outside = timewarp(image, rendered, camera(profile, "left", yaw=10.0))
    assert 0.0 < outside < 0.5
    np.testing.assert_allclose(warped[:, -1], 0.7, atol=1e-6)

    warped, outside = timewarp(image, rendered, camera(profile, "left", yaw=150.0))
    assert outside == 1.0
    np.testing.assert_array_equal(warped, 0.0)


def reference_warp(image: np.ndarray, rendered: EyeCamera, target: EyeCamera) -> np.ndarray:
    """The warp in NumPy from EyeCamera's own methods: clamped bilinear lookups, black behind the rendered eye."""
    h, w = image.shape[:2]
    ys, xs = np.mgrid[0:h, 0:w] + 0.5
    dirs = target.directions(np.stack([xs.ravel(), ys.ravel()], axis=1)).astype(np.float64)
    xy, _ = rendered.project(rendered.position + dirs)
    behind = (dirs @ rendered.rotation)[:, 2] >= 0
    fx = np.clip(np.nan_to_num(xy[:, 0]) - 0.5, 0, w - 1)
    fy = np.clip(np.nan_to_num(xy[:, 1]) - 0.5, 0, h - 1)
    x0, y0 = np.floor(fx).astype(int), np.floor(fy).astype(int)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    ax, ay = (fx - x0)[:, None], (fy - y0)[:, None]
    top = image[y0, x0] * (1 - ax) + image[y0, x1] * ax
    bottom = image[y1, x0] * (1 - ax) + image[y1, x1] * ax
    out = top * (1 - ay) + bottom * ay
    out[behind] = 0.0
    return out.reshape(h, w, 3)


@pytest.mark.parametrize(
    ("name", "eye", "yaw", "pitch", "roll"), [("dk2", "right", 4.0, -2.0, 1.0), ("sim-cpu", "left", 95.0, 10.0, 0.0)]
)
def test_every_pixel_matches_a_numpy_reference(name: str, eye: str, yaw: float, pitch: float, roll: float) -> None:
    """The homography stepped along rows and the clamped footprints agree with per-pixel projection; a turn past
    90 degrees puts part of the target behind the rendered eye (black) and part on the repeated edge."""
    profile = small(name)
    image = texture(profile)
    rendered, target = camera(profile, eye, 3.0, 1.0), camera(profile, eye, 3.0 + yaw, 1.0 + pitch, roll)
    warped = timewarp(image, rendered, target).image
    # float32 lookups land within ~2e-4 px of float64 ones, and a [0, 1] texture changes by at most 1 per pixel
    np.testing.assert_allclose(warped, reference_warp(image, rendered, target), atol=5e-4)


def float32_lookups_warp(image: np.ndarray, rendered: EyeCamera, target: EyeCamera) -> np.ndarray:
    """The warp with the kernel's own float32 lookups (each row's constant terms in float64, then float32 per pixel,
    coordinates clamped so that the footprint stays inside), blended from them in float64: what the kernel's output
    must match to float32 rounding of its blend, since 2026-12 as before (weights then, lerps with FMA now)."""
    f32 = np.float32
    h, w = image.shape[:2]
    m = homography(rendered, target)
    cy = np.arange(h)[:, None] + 0.5
    bx, by, bz = ((m[i, 0] * 0.5 + m[i, 1] * cy + m[i, 2]).astype(f32) for i in range(3))
    xf = np.arange(w, dtype=f32)[None, :]
    z = f32(m[2, 0]) * xf + bz
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = f32(1.0) / z
    qx, qy = (f32(m[0, 0]) * xf + bx) * inv, (f32(m[1, 0]) * xf + by) * inv
    fx = np.minimum(np.maximum(qx - f32(0.5), f32(0.0)), f32(w - 1))
    fy = np.minimum(np.maximum(qy - f32(0.5), f32(0.0)), f32(h - 1))
    ix, iy = np.clip(fx.astype(np.int32), 0, max(w - 2, 0)), np.clip(fy.astype(np.int32), 0, max(h - 2, 0))
    ax, ay = (fx - ix)[..., None].astype(np.float64), (fy - iy)[..., None].astype(np.float64)
    right, lower = np.minimum(ix + 1, w - 1), np.minimum(iy + 1, h - 1)
    top = image[iy, ix] * (1 - ax) + image[iy, right] * ax
    bottom = image[lower, ix] * (1 - ax) + image[lower, right] * ax
    out = top * (1 - ay) + bottom * ay
    out[~(z > 0)] = 0.0
    return out


@pytest.mark.parametrize(
    ("name", "eye", "yaw", "pitch", "roll"),
    [
        ("sim-cpu", "left", 1.5, 0.5, 0.0),  # the bench's turn
        ("dk2", "right", 4.0, -2.0, 1.0),
        ("vive_pro_eye", "left", 35.0, 30.0, 5.0),  # off two edges: the corner repeats
        ("vive_pro_eye", "right", -35.0, -30.0, -5.0),  # the opposite corner, the last texel's
        ("sim-cpu", "left", 95.0, 10.0, 0.0),  # part behind the rendered eye: black
    ],
)
def test_output_matches_the_float32_lookups_to_1e6(name: str, eye: str, yaw: float, pitch: float, roll: float) -> None:
    """Pinned to the lookups' float32 arithmetic: a [0, 1] texture comes out within 1e-6 (the blend's float32
    rounding) of float32_lookups_warp, which the SIMD blend of 2026-12 kept from the kernel before it (1.8e-7 apart
    on the bench's frames). A change to the projection, its clamping or its rounding moves pixels by far more."""
    profile = small(name)
    image = texture(profile, seed=3)
    rendered, target = camera(profile, eye, 3.0, 1.0), camera(profile, eye, 3.0 + yaw, 1.0 + pitch, roll)
    warped = timewarp(image, rendered, target).image
    np.testing.assert_allclose(warped, float32_lookups_warp(image, rendered, target), rtol=0, atol=1e-6)


@pytest.mark.parametrize(("width", "height"), [(1, 16), (16, 1), (1, 1), (2, 2), (37, 23)])
def test_images_down_to_one_pixel_read_only_their_own_texels(width: int, height: int) -> None:
    """The image sits inside NaNs: a read of anything but its texels (a step past a 1-pixel-wide row, a row past the
    last) would turn pixels NaN. Turns towards each corner clamp lookups onto the first and the last texels."""
    profile = get_profile("dk2").with_resolution(width, height)
    padded = np.full((height + 2, width, 3), np.nan, np.float32)
    padded[1:-1] = texture(profile)
    image = padded[1:-1]  # C-contiguous, NaN on both sides
    rendered = camera(profile, "left")
    for yaw, pitch in ((40.0, 40.0), (-40.0, -40.0), (40.0, -40.0), (-40.0, 40.0), (2.0, 1.0)):
        target = camera(profile, "left", yaw, pitch)
        warped = timewarp(image, rendered, target).image
        assert np.isfinite(warped).all()
        np.testing.assert_allclose(warped, float32_lookups_warp(image, rendered, target), rtol=0, atol=1e-6)


def test_every_split_into_bands_of_rows_gives_the_same_warp() -> None:
    """The kernel warps one band of rows per thread: every row is written once and counted once, however many
    bands (1 to one per row) and whatever the numba thread count the call runs on."""
    for width, height in ((24, 1), (24, 3), (192, 216)):
        profile = get_profile("sim-cpu").with_resolution(width, height)
        image, rendered, target = texture(profile), camera(profile, "left"), camera(profile, "left", 6.0, -3.0)
        whole = timewarp(image, rendered, target)
        assert 0.0 < whole.outside < 1.0
        for blocks in sorted({1, 2, 3, height}):
            out = np.full_like(image, np.nan)
            outside = _warp(Warp(image, out, homography(rendered, target)), blocks)
            np.testing.assert_array_equal(out, whole.image)
            assert outside / image[..., 0].size == whole.outside


def test_a_warp_into_a_buffer_allocates_nothing_image_sized() -> None:
    profile = get_profile("sim-cpu")
    image, out = texture(profile), np.empty((profile.height, profile.width, 3), np.float32)
    rendered, target = camera(profile, "left"), camera(profile, "left", 2.0, 1.0)
    timewarp(image, rendered, target, out)  # compiled
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    timewarp(image, rendered, target, out)
    peak = tracemalloc.get_traced_memory()[1] - before
    tracemalloc.stop()
    assert peak < 16 * 1024  # the image is 498 KB


def test_out_buffer_is_reused() -> None:
    profile = small("sim-cpu")
    image = texture(profile)
    out = np.full_like(image, np.nan)
    result = timewarp(image, camera(profile, "left"), camera(profile, "left", 3.0), out)
    assert result.image is out
    assert np.isfinite(out).all()


def test_mismatches_raise() -> None:
    profile = small("dk2")
    image = texture(profile)
    left, right = camera(profile, "left"), camera(profile, "right")
    other_size = camera(profile.with_resolution(profile.width, profile.height + 2), "left")
    with pytest.raises(ValueError, match="same eye"):
        timewarp(image, left, right)  # dk2's frusta are asymmetric: the eyes' tangents differ
    with pytest.raises(ValueError, match="same eye"):
        timewarp(image, left, other_size)
    with pytest.raises(ValueError, match="image must be"):
        timewarp(image[:-1], left, left)
    with pytest.raises(ValueError, match="out must be"):
        timewarp(image, left, left, np.empty((profile.height, profile.width, 3), np.float64))
    with pytest.raises(ValueError, match="out must be"):
        timewarp(image, left, left, np.empty((profile.height - 1, profile.width, 3), np.float32))
    with pytest.raises(ValueError, match="out must be"):
        timewarp(image, left, left, np.empty((profile.height, 2 * profile.width, 3), np.float32)[:, ::2])
    with pytest.raises(ValueError, match="overlap"):
        timewarp(image, left, left, image)
