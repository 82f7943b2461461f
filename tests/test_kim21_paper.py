"""kim21 against kim2021: pixel reuse after a saccade and under head motion (section 4.4), the interpolated
non-problematic subpixels of Figure 2, and Jin et al.'s selective supersampling of Table 2 as options."""

from __future__ import annotations

import numpy as np
import pytest

from hmdrt.evaluate.quality import band_psnr
from hmdrt.foveation import FrameRequest, make_method
from hmdrt.foveation.kim21.supersample import _resolve
from hmdrt.kernels.schedule import dynamic
from hmdrt.optics import get_profile
from hmdrt.optics.projection import bilinear3
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose, gaze_direction, quat_multiply
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import FrameInput, eye_cameras, frame_requests

PROFILE = get_profile("sim-cpu").with_resolution(128, 144)
PIXEL_DEG = 0.895  # degrees per pixel at the image centre: 2 tan 45 degrees over 128 pixels
REFERENCE = "regular?spp=16"
# Table 2's Selective (kim2021 sections 3, 4.6.2 and 5): a constant tau_fov, four samples per problematic subpixel,
# the presampled colour in the others, no reuse, no smoothing
SELECTIVE = (
    "kim21?tau_0=1&tau_f=1&tau_f_slope=0&tau_np=1&n_f=4&n_p=4&n_m=4&n_np=4&interpolate=false&reuse=false&smooth=false"
)


def requests(inputs: list[FrameInput]) -> list[FrameRequest]:
    return [frame_requests(inp, eye_cameras(PROFILE, inp.pose, ("left",)), 0)[0] for inp in inputs]


def band_psnrs(tracer: Whitted, spec: str, frames: list[FrameRequest], truth: list[np.ndarray]) -> list[dict]:
    """Per frame: band_psnr of `spec`'s image against the truth, with the frame's reused pixels."""
    method, out = make_method(spec, tracer), []
    for request, reference in zip(frames, truth, strict=True):
        stats = FrameStats()
        image = method.render(request, stats)
        out.append({**band_psnr(image, reference, request.camera.eccentricity(request.gaze)), **stats.metrics})
    return out


def truths(tracer: Whitted, frames: list[FrameRequest]) -> list[np.ndarray]:
    """The regular 16 spp truth of each frame, rendered once per camera pose."""
    reference, images = make_method(REFERENCE, tracer), {}
    keys = [r.camera.position.tobytes() + r.camera.rotation.tobytes() for r in frames]
    for key, request in zip(keys, frames, strict=True):
        if key not in images:
            images[key] = reference.render(request, FrameStats())
    return [images[key] for key in keys]


def reuse_against_no_reuse(inputs: list[FrameInput], first: int) -> tuple[list[dict], list[dict]]:
    """Frames `first` on of kim21 with and without reuse, each against the regular 16 spp truth."""
    scene = load_scene("whitted")
    frames = requests(inputs)
    with Whitted(scene) as tracer:
        truth = truths(tracer, frames)
        runs = [band_psnrs(tracer, spec, frames, truth)[first:] for spec in ("kim21", "kim21?reuse=false")]
    return runs[0], runs[1]


def test_reuse_after_a_saccade_keeps_the_new_foveas_quality():
    """Section 4.4: a pixel whose colour was rendered at a lower class than its band needs now (the new fovea and
    parafovea were in the perifovea and near periphery before a 15 degree saccade) is rendered again, so none of the
    five frames after the saccade is worse than the worst of them rendered without reuse, which vary by a few dB
    with the jitter of the extra samples (drawn anew each frame); copying the one-sample colours would cost the
    fovea 8-10 dB for two frames."""
    start = load_scene("whitted").start
    inputs = [
        FrameInput(f, f * PROFILE.period_ns, start, {"left": np.array(gaze_direction(*gaze))})
        for f, gaze in enumerate([(0.0, 0.0)] * 4 + [(-12.0, -9.0)] * 5)
    ]
    reused, fresh = reuse_against_no_reuse(inputs, 4)
    assert all(r["reused_pixels"] > 0.3 * r["central_pixels"] for r in reused[1:])
    for band in ("fovea", "parafovea"):
        worst = min(f[band] for f in fresh)
        assert all(r[band] > worst - 1.0 for r in reused), band


def yawed(pose: Pose, degrees: float) -> Pose:
    """The head pose turned by `degrees` of yaw."""
    turn = Pose.looking((0.0, 0.0, 0.0), degrees, 0.0).orientation
    return Pose(pose.position, quat_multiply(pose.orientation, turn))


def test_reuse_under_head_motion_keeps_the_foveas_quality():
    """Section 4.4's nearest-pixel copy at 0.8 pixels of yaw per frame: a copy whose colour was rendered more than
    reuse_px away from where the pixel looks now (its drift summed over the chain of copies) is refused, so the fovea
    loses under 1.5 dB to reuse over the frames (4.5 dB without the bound)."""
    start, gaze = load_scene("whitted").start, np.array(gaze_direction(0.0, 0.0))
    inputs = [FrameInput(f, f * PROFILE.period_ns, yawed(start, 0.8 * PIXEL_DEG * f), {"left": gaze}) for f in range(8)]
    reused, fresh = reuse_against_no_reuse(inputs, 2)
    assert sum(r["reused_pixels"] for r in reused) > 0
    assert np.mean([r["fovea"] for r in reused]) > np.mean([f["fovea"] for f in fresh]) - 1.5


def interpolated(image: np.ndarray, x: int, y: int, s: int) -> np.ndarray:
    """bilinear3 at the centre of pixel (x, y)'s subpixel s (NW, NE, SW, SE)."""
    return np.array(bilinear3(image, x + 0.25 + 0.5 * (s & 1), y + 0.25 + 0.5 * (s >> 1)))


@pytest.mark.parametrize("interpolate", [True, False])
def test_resolve_interpolates_the_subpixels_that_are_not_problematic(interpolate):
    """Figure 2: a rendered central pixel is the mean of its four subpixels, the non-problematic ones interpolated
    from the four surrounding pixel centres (the presampled colour with interpolate=false, Jin et al.); a pixel
    with no problematic subpixel too. Reused and peripheral pixels keep what they hold."""
    h, w = 4, 5
    rng = np.random.default_rng(1)
    image = rng.random((h, w, 3), dtype=np.float32)
    samples = np.full(h * w, 2, np.uint8)
    samples[3] = 0  # peripheral
    flags = np.zeros(h * w, np.int32)
    flags[7] = 1  # reused
    sub_mask = np.zeros(h * w, np.uint8)
    sub_mask[12] = 0b0010  # NE problematic
    first = np.array([0, 0, 0, 2, 2], np.int64)  # pixel 12 (row 2) has the two extra samples
    extra = np.array([[1.0, 2.0, 3.0], [3.0, 4.0, 5.0]], np.float32)
    held = rng.random((h * w, 3), dtype=np.float32)
    out = held.copy()
    spans = np.array([[0, w], [0, w], [0, w], [0, w]], np.int64)  # each row's central columns, the peripheral one too
    dynamic(_resolve, image, sub_mask, samples, spans, flags, first, extra, interpolate, out)
    for i in range(h * w):
        y, x = divmod(i, w)
        if i in (3, 7):
            want = held[i]
        elif i == 12:
            subpixels = [interpolated(image, x, y, s) if interpolate else image[y, x] for s in range(4)]
            subpixels[1] = extra.mean(axis=0)
            want = np.mean(subpixels, axis=0)
        else:
            want = np.mean([interpolated(image, x, y, s) for s in range(4)], axis=0) if interpolate else held[i]
        np.testing.assert_allclose(out[i], want, rtol=1e-5, err_msg=f"pixel {i}")


def test_selective_supersamples_like_jin_et_al():
    """Table 2's Selective: four samples per problematic subpixel in the central region, every other pixel the
    presampled colour at its centre (`full`'s image)."""
    scene = load_scene("whitted")
    (request,) = requests([FrameInput(0, 0, scene.start, {"left": np.array(gaze_direction(-4.0, -8.0))})])
    with Whitted(scene) as tracer:
        full = make_method("full", tracer).render(request, FrameStats())
        stats = FrameStats()
        image = make_method(SELECTIVE, tracer).render(request, stats)
    problematic = stats.metrics["problematic_subpixels"]
    assert problematic > 0 and stats.metrics["extra_samples"] == 4 * problematic
    changed = (image != full).any(axis=-1)
    assert 0 < changed.sum() <= problematic
    assert not changed[request.camera.eccentricity(request.gaze) >= 30.0].any()


def test_the_presample_keeps_table_1_for_the_central_pixels_and_their_neighbours():
    """What the tests read of Table 1 (the inspection compares a central pixel with its neighbours): Foveation.table1
    is the central region (e < e_np) grown by one pixel, the presample's GBuffer.kept, and Foveation.spans each row's
    central columns; an off-centre gaze at a small size, so that the region meets the image's edges."""
    from hmdrt.foveation.kim21.bands import Foveation, _foveation, alpha_knots, bezier_controls
    from hmdrt.foveation.kim21.params import Kim21Params
    from hmdrt.optics.camera import EyeCamera, eccentricity_map

    p = Kim21Params()
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(40, 30), load_scene("whitted").start)
    ecc = eccentricity_map(cam, np.array(gaze_direction(35.0, 10.0)))
    fov = Foveation.empty(*ecc.shape)
    bounds = np.array([p.e_f, p.e_p, p.e_m])
    counts = np.array([p.n_f, p.n_p, p.n_m, p.n_np], np.uint8)
    _foveation(ecc, bezier_controls(p), bounds, counts, p.e_np, alpha_knots(p), np.array(p.alpha), fov)
    central = (ecc < p.e_np).reshape(-1)
    np.testing.assert_array_equal(fov.samples > 0, central)
    grown = np.pad(central.reshape(ecc.shape), 1)
    near = np.zeros(ecc.shape, bool)
    for dy in range(3):
        for dx in range(3):
            near |= grown[dy : dy + ecc.shape[0], dx : dx + ecc.shape[1]]
    np.testing.assert_array_equal(fov.table1, near.reshape(-1))
    assert central.any() and not near.all() and near.sum() > central.sum()
    rows = central.reshape(ecc.shape)
    for y, row in enumerate(rows):  # the columns the inspection's contrast boxes are computed for
        xs = np.flatnonzero(row)
        assert tuple(fov.spans[y]) == ((xs[0], xs[-1] + 1) if len(xs) else (0, 0))
    assert not rows.all(axis=1).all() and not rows.any(axis=1).all()
