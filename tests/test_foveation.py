"""The foveated methods: convergence, full-rate foveae, paper behaviours, stage pruning, determinism."""

import numpy as np
import pytest

from hmdrt.errors import ConfigError
from hmdrt.foveation import METHODS, FrameRequest, make_method
from hmdrt.foveation.base import EYES
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.quality import band_psnr
from hmdrt.scene import load_scene
from hmdrt.sequence import FrameInput, builtin_path, render_frames
from hmdrt.spatial import gaze_direction
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

FOVEATED = ["rrm", "kim21", "weier16", "weier18"]
PROFILE = get_profile("sim-cpu").with_resolution(96, 108)


def still(scene, frames, gaze=(0.0, 0.0)):
    g = gaze_direction(*gaze)
    return [FrameInput(f, f * PROFILE.period_ns, scene.start, {"left": g, "right": g}) for f in range(frames)]


def run(spec, scene_name, inputs_fn, eyes=("left",), profile=PROFILE):
    scene = load_scene(scene_name)
    with Whitted(scene) as tracer:
        method = make_method(spec, tracer)
        out = []
        for _, images, stats in render_frames(method, profile, inputs_fn(scene), eyes):
            out.append(([im.copy() for im in images], stats))
    return out


@pytest.mark.parametrize("spec", FOVEATED)
def test_a_still_view_converges(spec):
    frames = run(spec, "whitted", lambda s: still(s, 16, (6.0, -3.0)))
    changes = [np.abs(a[0][0] - b[0][0]).mean() for a, b in zip(frames, frames[1:], strict=False)]
    assert changes[-1] < 1e-3 * frames[-1][0][0].mean()
    assert changes[-1] <= changes[0]
    assert all(np.all(np.isfinite(f[0][0])) for f in frames)


def test_rrm_resolves_a_still_scene_to_the_full_image_after_n_frames():
    full = run("full", "whitted", lambda s: still(s, 1))[0][0][0]
    for order in ("horizontal", "serpentine", "scattered"):
        frames = run(f"rrm?order={order}", "whitted", lambda s: still(s, 13))
        assert not np.array_equal(frames[10][0][0], full)  # the periphery is not complete before N frames
        np.testing.assert_array_equal(frames[11][0][0], full)  # N = 12 frames later, all of it is fresh


@pytest.mark.parametrize("spec", ["weier16", "rrm"])
def test_the_fovea_is_traced_fresh_every_frame_while_the_head_moves(spec):
    scene = load_scene("whitted")
    inputs = builtin_path(6, PROFILE.period_ns, scene.start, seed=2)
    fov = run(spec, "whitted", lambda s: inputs)
    ref = run("full", "whitted", lambda s: inputs)
    radius = 9.5 if spec == "weier16" else 9.0  # weier16: inside r0 = 10 deg; rrm: inside its +-10 deg rectangle
    for inp, (images, _), (full, _) in zip(inputs, fov, ref, strict=True):
        cam = EyeCamera.for_eye(PROFILE, inp.pose, "left")
        fovea = cam.eccentricity(inp.gaze["left"]) < radius
        assert fovea.sum() > 100
        np.testing.assert_array_equal(images[0][fovea], full[0][fovea])


def test_kim21_supersamples_the_fovea_closer_to_the_ground_truth_than_one_sample():
    scene = load_scene("whitted")
    gaze = gaze_direction(-4.0, -8.0)  # on the glass sphere's edge and the checkerboard
    cam = EyeCamera.for_eye(PROFILE, scene.start)
    with Whitted(scene) as tracer:
        req = FrameRequest(cam, gaze)
        truth = make_method("regular?spp=36", tracer).render(req, FrameStats())
        full = make_method("full", tracer).render(req, FrameStats())
        stats = FrameStats()
        kim = make_method("kim21?reuse=false&smooth=false", tracer).render(req, stats)
    ecc = cam.eccentricity(gaze)
    p_full, p_kim = band_psnr(full, truth, ecc), band_psnr(kim, truth, ecc)
    assert p_kim["fovea"] > p_full["fovea"] + 3.0
    assert p_kim["far_periphery"] == pytest.approx(p_full["far_periphery"])  # one sample per pixel out there
    assert stats.metrics["extra_samples"] > 0 and stats.rays["primary"] == ecc.size + stats.metrics["extra_samples"]


def test_kim21_reuses_pixels_of_a_still_view():
    frames = run("kim21", "whitted", lambda s: still(s, 3))
    assert frames[0][1].metrics["reused_pixels"] == 0
    assert frames[2][1].metrics["reused_pixels"] > 0.5 * frames[2][1].metrics["central_pixels"]


def test_weier18_focuses_where_the_gaze_rests():
    # gaze at the big blue ball 6 m away (front at 5.2 m) and at the first target about 0.6 m away
    far = run("weier18", "shooting_range", lambda s: still(s, 1, (0.0, -2.9)))[0][1].metrics["focus_m"]
    near = run("weier18", "shooting_range", lambda s: still(s, 1, (21.8, -5.2)))[0][1].metrics["focus_m"]
    assert 5.0 < far < 5.5 and 0.45 < near < 0.65


def test_weier18_depth_of_field_blurs_only_out_of_focus():
    profile = get_profile("sim-cpu").with_resolution(320, 360)  # enough pixels per degree for visible blur
    look = lambda s: still(s, 1, (0.0, -2.9))  # noqa: E731
    sharp = run("weier18?dof=none&contrast=0", "shooting_range", look, profile=profile)[0][0][0]
    blurred = run("weier18?dof=strong&contrast=0", "shooting_range", look, profile=profile)[0][0][0]
    scene = load_scene("shooting_range")
    cam = EyeCamera.for_eye(profile, scene.start)
    depth = cam_depth(scene, cam)
    focused = np.abs(depth - 5.2) < 0.15  # the ball, inside the focus range
    near = depth < 2.0  # targets and floor well in front of it
    diff = np.abs(blurred - sharp).mean(axis=2)
    assert diff[near].mean() > 5 * diff[focused].mean()


def cam_depth(scene, cam):
    from hmdrt.optics.camera import pixel_centres
    from hmdrt.trace.gbuffer import GBuffer

    with Whitted(scene) as tracer:
        g = GBuffer.empty(cam.width * cam.height)
        tracer.trace_samples(
            cam, pixel_centres(cam.width, cam.height), np.arange(cam.width * cam.height), FrameStats(), g
        )
    return g.primary.depth.reshape(cam.height, cam.width)


def test_stages_follow_what_the_scene_and_config_need():
    def stages(spec, scene, frames=2):
        return set(run(spec, scene, lambda s: still(s, frames))[-1][1].stages_ms)

    whitted = stages("weier16", "whitted")
    tunnel = stages("weier16", "tunnel_maps")
    interior = stages("weier16", "interior")
    assert "trace/secondary" in whitted and not any("secondary" in k for k in tunnel)
    assert "post" in interior and "post" not in whitted and "post" not in tunnel  # needs area lights or AO
    assert {"reproject", "resample_info"} <= whitted
    first = set(run("weier16", "whitted", lambda s: still(s, 1))[0][1].stages_ms)
    assert "reproject" not in first and "resample_info" not in first  # no previous frame yet
    assert not {"gaze_depth", "coc", "dof_filter"} & stages("weier18?dof=none", "whitted")
    assert {"gaze_depth", "coc", "dof_filter", "taa"} <= stages("weier18", "whitted")
    assert "combine" in stages("weier18?contrast=0&dof=none", "whitted")  # the one pass that writes the image


def test_skipped_stages_cost_nothing_and_rays_are_counted():
    _, tunnel = run("weier16", "tunnel_maps", lambda s: still(s, 2))[-1]
    assert tunnel.rays["secondary"] == 0 and tunnel.rays["ao"] == 0 and tunnel.rays["area"] == 0
    assert tunnel.rays["primary"] > 0 and tunnel.rays["shadow"] > 0


@pytest.mark.parametrize("spec", FOVEATED)
def test_sequences_reproduce_bit_for_bit(spec):
    scene = load_scene("interior")
    inputs = builtin_path(3, PROFILE.period_ns, scene.start, seed=4)
    a = run(spec, "interior", lambda s: inputs)
    b = run(spec, "interior", lambda s: inputs)
    for (ia, _), (ib, _) in zip(a, b, strict=True):
        np.testing.assert_array_equal(ia[0], ib[0])


@pytest.mark.parametrize("spec", sorted(METHODS))
@pytest.mark.parametrize("scene_name", ["whitted", "interior"])
def test_an_image_once_returned_is_never_written_again(spec, scene_name):
    """The compositor hands a method's images to the display and the frame writer without copying them."""
    scene = load_scene(scene_name)
    inputs = builtin_path(4, PROFILE.period_ns, scene.start, seed=2)
    with Whitted(scene) as tracer:
        method = make_method(spec, tracer)
        kept = [
            (image, image.copy()) for _, images, _ in render_frames(method, PROFILE, inputs, EYES) for image in images
        ]
    assert len({id(image) for image, _ in kept}) == len(kept)
    for image, copy in kept:
        np.testing.assert_array_equal(image, copy)


def test_each_eye_keeps_its_own_history():
    frames = run("weier16", "whitted", lambda s: still(s, 6), eyes=("left", "right"))
    left, right = frames[-1][0]
    assert not np.array_equal(left, right)  # the eyes are 63.5 mm apart
    solo = run("weier16", "whitted", lambda s: still(s, 6), eyes=("right",))[-1][0][0]
    np.testing.assert_array_equal(right, solo)  # rendering the left eye too changed nothing for the right


@pytest.mark.parametrize(
    "spec,message",
    [
        ("weier16?frc=huge", "frc"),
        ("weier16?r0=30&r1=20", "must not exceed"),
        ("weier16?k_min=0.9&k_max=0.5", "k_min must not exceed"),
        ("kim21?e_f=20", "e_f <= e_p"),
        ("kim21?n_f=17", "n_f"),
        ("rrm?order=diagonal", "order"),
        ("weier18?dof=blurry", "dof"),
        ("weier18?r0=25", "r0 must not exceed r1"),
        ("rrm?speed=2", "unknown field `speed`"),
    ],
)
def test_bad_method_options_are_refused(spec, message):
    scene = load_scene("whitted")
    with Whitted(scene) as tracer, pytest.raises(ConfigError, match=message):
        make_method(spec, tracer)


def test_every_method_is_registered():
    assert set(METHODS) == {"full", "regular", "rrm", "kim21", "weier16", "weier18"}
