"""kim21 over time (kim2021): the stratified jittered extra samples of section 4.6.2 are drawn afresh every frame,
so that section 4.7's smoothing averages them on a still view, and the closed form's null colour of a rejected
earlier frame."""

from __future__ import annotations

import numpy as np

from hmdrt.foveation import FrameRequest, make_method
from hmdrt.foveation.stages.temporal import History, exponential_smoothing
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose, gaze_direction
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

PROFILE = get_profile("sim-cpu").with_resolution(96, 108)
GAZE = np.array(gaze_direction(-4.0, -8.0))  # on the glass sphere's edge and the checkerboard


def still_frames(spec: str, frames: list[int]) -> tuple[list[np.ndarray], list[FrameStats], EyeCamera]:
    """`spec`'s images of the still view at GAZE, one method rendering the given frame numbers in turn."""
    scene = load_scene("whitted")
    cam = EyeCamera.for_eye(PROFILE, scene.start)
    images, stats = [], []
    with Whitted(scene) as tracer:
        method = make_method(spec, tracer)
        for f in frames:
            stats.append(FrameStats())
            images.append(method.render(FrameRequest(cam, GAZE, f), stats[-1]).copy())
    return images, stats, cam


def test_the_supersampling_jitter_is_drawn_afresh_every_frame():
    """Section 4.6.2: the extra rays are stratified and jittered, with new jitter each frame: on a still view the
    presample, and with it the problematic subpixels, stay, the extra samples' colours change; the same frame
    number renders the same image (seeded)."""
    spec = "kim21?reuse=false&smooth=false"
    (a, b), (sa, sb), cam = still_frames(spec, [0, 1])
    (again,), _, _ = still_frames(spec, [0])
    np.testing.assert_array_equal(a, again)
    assert sa.metrics["extra_samples"] == sb.metrics["extra_samples"] > 0
    changed = (a != b).any(axis=-1)
    assert changed.sum() > 0.3 * sa.metrics["problematic_subpixels"] / 4  # pixels, at up to 4 subpixels each
    assert not changed[cam.eccentricity(GAZE) >= 30.0].any()  # one sample at the centre out there, every frame


def test_smoothing_averages_the_jitter_of_a_still_view():
    """Section 4.7 and Table 3: on a still view, smoothing blends frames of independent jitter, so the image
    changes less from frame to frame than without it."""
    frames = list(range(8))
    flicker = {}
    for smooth in ("true", "false"):
        images, _, cam = still_frames(f"kim21?reuse=false&smooth={smooth}", frames)
        central = cam.eccentricity(GAZE) < 30.0
        changes = [np.abs(x - y)[central].mean() for x, y in zip(images[4:-1], images[5:], strict=True)]
        flicker[smooth] = np.mean(changes)
    assert 0.0 < flicker["true"] < 0.6 * flicker["false"]


def test_a_rejected_earlier_frame_is_left_out_of_the_closed_form():
    """Section 4.7's null colour: an earlier frame whose back-projected pixel sees another surface adds nothing to
    either sum of the closed form (a black colour with its weight kept would darken every disocclusion, and the
    periphery, at alpha 0.1, to a quarter of its colour)."""
    h, w = 6, 8
    cam = EyeCamera.for_eye(get_profile("rift_s").with_resolution(w, h), Pose.looking((0.0, 1.6, 0.0)))
    rng = np.random.default_rng(2)
    c0, c1, c2 = (rng.uniform(0.2, 1.0, (h, w, 3)).astype(np.float32) for _ in range(3))
    depth = np.full((h, w), 2.0, np.float32)
    other = np.full((h, w), 3.0, np.float32)  # 50% off: beyond any depth tolerance
    alpha = np.full((h, w), 0.1, np.float32)
    keep = 1.0 - np.float32(0.1)
    for older, newer, expected in (
        (other, other, c0),  # both rejected: the frame's own colour
        (depth, other, (c0 + keep * keep * c1) / (1.0 + keep * keep)),  # the newer rejected
    ):
        history = History(4)
        history.push(cam, older, c1)
        history.push(cam, newer, c2)
        out = exponential_smoothing(cam, depth, c0, alpha, history, 4, 0.02)
        np.testing.assert_allclose(out, expected, rtol=1e-6)


def test_the_colour_ring_keeps_a_spare_float_after_its_last_texel():
    """The still view's smoothing reads an earlier frame's texel as four floats (simd.rgb_accumulate): after the
    ring's last texel lies a float of its own buffer, so that read stays inside it."""
    history = History(4)
    history.begin((5, 7))
    owner = history.color
    while owner.base is not None:
        owner = owner.base
    start = history.color.__array_interface__["data"][0]
    assert start == owner.__array_interface__["data"][0]
    assert owner.nbytes >= history.color.nbytes + 4
