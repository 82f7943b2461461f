"""The foveated methods: convergence, full-rate foveae, paper behaviours, stage pruning, determinism."""

import msgspec
import numpy as np
import pytest
from scipy import ndimage

from hmdrt.errors import ConfigError
from hmdrt.evaluate.quality import band_psnr
from hmdrt.foveation import METHODS, FrameRequest, MethodChoice, make_method
from hmdrt.foveation.base import EYES, pixel_keys
from hmdrt.foveation.registry import temporal_methods
from hmdrt.foveation.rrm import Rrm, RrmParams, foveal_rectangle
from hmdrt.foveation.stages.dof import MAX_BLUR_PX
from hmdrt.foveation.stages.refresh import RefreshSchedule, refresh_phase
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.scene import load_scene
from hmdrt.spatial import gaze_direction
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import FrameInput, builtin_path, render_frames

FOVEATED = temporal_methods()  # rrm, kim21, weier16, weier18 (base.Checks.temporal)
PROFILE = get_profile("sim-cpu").with_resolution(96, 108)


def still(scene, frames, gaze=(0.0, 0.0)):
    g = np.array(gaze_direction(*gaze))
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
    # no growth; kim21 draws its extra samples' jitter afresh each frame, and renders every 6th frame afresh (after
    # n_reuse_max = 5 reuses), which changes it most (tests/test_kim21_temporal.py)
    assert changes[-1] <= max(changes[:6])
    assert all(np.all(np.isfinite(f[0][0])) for f in frames)


def test_rrm_resolves_a_still_scene_to_the_full_image_after_n_frames():
    full = run("full", "whitted", lambda s: still(s, 1))[0][0][0]
    for order in ("horizontal", "serpentine", "scattered"):
        frames = run(f"rrm?order={order}", "whitted", lambda s: still(s, 13))
        assert not np.array_equal(frames[10][0][0], full)  # the periphery is not complete before N frames
        np.testing.assert_array_equal(frames[11][0][0], full)  # N = 12 frames later, all of it is fresh


class RecordingTracer:
    """Stands in for Whitted: records the samples asked for and answers each with its key as radiance."""

    def __init__(self):
        self.calls = []

    def trace_samples(self, camera, xy, keys, stats, out):
        self.calls.append((xy.copy(), keys.copy()))
        out[:] = keys[:, None]
        return out


@pytest.mark.parametrize(
    "options, gaze",
    [
        ({}, (0.0, 0.0)),
        ({"order": "scattered", "block": 3}, (20.0, -10.0)),
        ({"order": "serpentine", "group_w": 5, "group_h": 2, "fovea_deg": 30.0}, (-40.0, 30.0)),
        ({"fovea_deg": 5.0}, (80.0, 0.0)),  # the rectangle off the image: the periphery alone
    ],
)
def test_rrm_traces_its_cell_and_the_foveal_rectangle_in_row_major_order(options, gaze):
    """Each frame samples the pixels of refresh_phase's phase for the frame and the foveal rectangle, as pixel
    centres in row-major order with base.pixel_keys, and the image is the buffer they were written into."""
    profile = get_profile("sim-cpu").with_resolution(61, 23)  # not multiples of the group or the block
    scene = load_scene("whitted")
    cam = EyeCamera.for_eye(profile, scene.start)
    params = RrmParams(**options, smoothing=1.0)
    tracer = RecordingTracer()
    method = Rrm(tracer, params)
    phase = refresh_phase(cam.width, cam.height, params)
    g = np.array(gaze_direction(*gaze))
    x0, x1, y0, y1 = foveal_rectangle(cam, g, params)
    expected = np.zeros((cam.height, cam.width, 3), np.float32)
    out = np.full_like(expected, np.nan)
    for frame in range(params.cycle + 2):
        mask = phase == frame % params.cycle
        mask[y0:y1, x0:x1] = True
        pixels = np.flatnonzero(mask)
        image = method.render(FrameRequest(cam, g, frame, seed=3), FrameStats(), out)
        xy, keys = tracer.calls[-1]
        np.testing.assert_array_equal(xy, np.stack([pixels % cam.width, pixels // cam.width], axis=1) + 0.5)
        np.testing.assert_array_equal(keys, pixel_keys(pixels, 3))
        expected.reshape(-1, 3)[pixels] = keys[:, None]
        assert image is out
        np.testing.assert_array_equal(image, expected)


def test_rrm_refreshes_the_stalest_cells_first_when_its_cycle_changes():
    """With group_w moved every few frames (as the budget controller does), each eye traces the cells its
    RefreshSchedule gives, and every peripheral pixel is refreshed within the new N frames of the last change."""
    profile = get_profile("sim-cpu").with_resolution(61, 23)
    cam = EyeCamera.for_eye(profile, load_scene("whitted").start)
    g = np.array(gaze_direction(80.0, 0.0))  # the foveal rectangle off the image: the periphery alone
    tracer, schedule = RecordingTracer(), RefreshSchedule()
    method = Rrm(tracer, RrmParams(smoothing=1.0))
    cycles = [3, 3, 5, 1, 4, 4, 2, 5, 3, 1, 1, 5, 2] + [4] * 16
    last = np.full((cam.height, cam.width), -1)
    for frame, group_w in enumerate(cycles, start=40):
        params = RrmParams(group_w=group_w, smoothing=1.0)
        method.set_params(params)
        method.render(FrameRequest(cam, g, frame, seed=3), FrameStats())
        mask = refresh_phase(cam.width, cam.height, params) == schedule.phase(frame, cam.width, params)
        xy, _ = tracer.calls[-1]
        np.testing.assert_array_equal(xy, np.stack(np.nonzero(mask)[::-1], axis=1) + 0.5)
        last[mask] = frame
    assert np.all(last >= 40 + len(cycles) - 16)


def test_rrm_refuses_an_out_buffer_of_another_shape():
    cam = EyeCamera.for_eye(PROFILE, load_scene("whitted").start)
    method = Rrm(RecordingTracer(), RrmParams())
    with pytest.raises(ValueError, match="out must be a float32 array of shape"):
        method.render(
            FrameRequest(cam, np.array(gaze_direction(0.0, 0.0))), FrameStats(), np.empty((4, 4, 3), np.float32)
        )


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
    gaze = np.array(gaze_direction(-4.0, -8.0))  # on the glass sphere's edge and the checkerboard
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


def test_kim21_on_a_still_view_matches_back_projection():
    """Reuse and smoothing read a still camera's earlier frames in place; a camera 1 nm away back-projects."""
    scene = load_scene("whitted")
    cam = EyeCamera.for_eye(PROFILE, scene.start)
    nudged = EyeCamera(**{**cam.__dict__, "position": cam.position + 1e-9})
    gaze = np.array(gaze_direction(-4.0, -8.0))
    frames = []
    with Whitted(scene) as tracer:
        for cameras in ([cam] * 4, [cam, nudged, cam, nudged]):
            method = make_method("kim21", tracer)
            stats = [FrameStats() for _ in cameras]
            images = [
                method.render(FrameRequest(c, gaze, f), s) for f, (c, s) in enumerate(zip(cameras, stats, strict=True))
            ]
            frames.append((images, [s.metrics["reused_pixels"] for s in stats]))
    (still_images, still_reused), (moved_images, moved_reused) = frames
    assert still_reused == moved_reused and still_reused[-1] > 0
    for a, b in zip(still_images, moved_images, strict=True):
        np.testing.assert_allclose(a, b, atol=1e-5)


def test_kim21_renders_into_the_callers_buffer_and_leaves_returned_images_alone():
    scene = load_scene("whitted")
    inputs = builtin_path(3, PROFILE.period_ns, scene.start)
    outs = [np.empty((PROFILE.height, PROFILE.width, 3), np.float32) for _ in range(2)]
    with Whitted(scene) as tracer:
        method = make_method("kim21", tracer)
        shown = []
        for inp, out in zip(inputs, [outs[0], outs[1], None], strict=True):
            cam = EyeCamera.for_eye(PROFILE, inp.pose, "left")
            image = method.render(FrameRequest(cam, inp.gaze["left"], inp.frame), FrameStats(), out)
            assert out is None or image is out
            shown.append((image, image.copy()))
    assert shown[2][0] is not outs[0] and shown[2][0] is not outs[1]
    for image, copy in shown:
        np.testing.assert_array_equal(image, copy)  # later frames never wrote into an earlier frame's image


def test_kim21_foveation_follows_the_gaze_and_the_parameters():
    """Bands are derived once per change of gaze or parameters, and every change takes effect."""
    scene = load_scene("whitted")
    cam = EyeCamera.for_eye(PROFILE, scene.start)
    with Whitted(scene) as tracer:
        method = make_method("kim21?tau_0=1&tau_f=1&tau_f_slope=0&tau_np=1", tracer)  # any e_np is valid
        for f, (gaze, e_np) in enumerate([((0, 0), 30.0), ((0, 0), 30.0), ((20, 5), 30.0), ((20, 5), 12.5)]):
            if e_np != method.params.e_np:
                method.set_params(msgspec.structs.replace(method.params, e_np=e_np))
            g = np.array(gaze_direction(*gaze))
            stats = FrameStats()
            method.render(FrameRequest(cam, g, f), stats)
            assert stats.metrics["central_pixels"] == (cam.eccentricity(g) < e_np).sum()


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
    # the near field's blur spreads over what lies behind it (alpha-blended, section 3.2); beyond its reach the
    # ball in focus is left exactly as it was
    clear = focused & (ndimage.distance_transform_edt(~near) > MAX_BLUR_PX)
    assert clear.sum() > 0.5 * focused.sum()
    assert diff[near].mean() > 0.004 and diff[clear].max() < 1e-5


def test_weier18_density_option_redraws_its_sampling_tables():
    """density=linear (equation (1) with the polar Jacobian) traces another set of pixels, also when set on a
    running method; the printed equation stays the default."""
    profile = get_profile("sim-cpu").with_resolution(320, 360)
    look = lambda s: still(s, 1)  # noqa: E731
    fraction = lambda frames: frames[0][1].metrics["sample_fraction"]  # noqa: E731
    printed = fraction(run("weier18?dof=none", "whitted", look, profile=profile))
    linear = fraction(run("weier18?dof=none&density=linear", "whitted", look, profile=profile))
    assert printed != linear and make_method("weier18", None).params.density == "printed"
    scene = load_scene("whitted")
    with Whitted(scene) as tracer:
        method = make_method("weier18?dof=none", tracer)
        request = FrameRequest(EyeCamera.for_eye(profile, scene.start), np.array(gaze_direction(0.0, 0.0)), 0)
        method.render(request, FrameStats())
        method.set_params(msgspec.structs.replace(method.params, density="linear"))
        stats = FrameStats()
        method.render(request, stats)
    assert stats.metrics["sample_fraction"] == linear


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


def test_image_space_stages_say_how_much_memory_they_must_touch():
    """bench/stage_budget.py sets each image-space stage against a copy of the bytes it declares: every method's
    full-resolution passes (Stage.touches) declare them, the tracer's stages (bounded by rays, not bytes) do not."""
    declared = {name: {s.name for s in cls.stages if s.touches} for name, cls in METHODS.items()}
    image = PROFILE.width * PROFILE.height * 3 * np.dtype(np.float32).itemsize
    for spec, stages in declared.items():
        stats = run(spec, "whitted", lambda s: builtin_path(2, PROFILE.period_ns, s.start))[-1][1]
        assert set(stats.touched) == stages, spec
        assert all(stats.touched[name] >= image for name in stages), (spec, stats.touched)
        assert stats.touched.get("combine", 2 * image) >= 2 * image  # weier18's reads its input and writes out


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


@pytest.mark.parametrize(
    "spec,written",
    [
        ("full", "full"),
        ("rrm?fovea_deg=10.0", "rrm"),  # the default is not written
        ("rrm?group_w=2&fovea_deg=8", "rrm?fovea_deg=8.0&group_w=2"),  # field order, typed values
        ("weier16?frc=small&post=false", "weier16?frc=small&post=false"),
        ("regular?spp=4", "regular?spp=4"),
        ("kim21?alpha=0.5,0.5,0.5,0.5,0.5,0.4", "kim21?alpha=0.5,0.5,0.5,0.5,0.5,0.4"),  # a list: its values
    ],
)
def test_a_method_choice_is_parsed_once_and_written_back_as_it_reads(spec, written):
    choice = MethodChoice.parse(spec)
    assert str(choice) == written and MethodChoice.parse(written) == choice
    assert choice.params == METHODS[choice.name].Params(**msgspec.structs.asdict(choice.params))


def test_a_method_choice_changes_its_options_with_the_same_checks():
    choice = MethodChoice.parse("weier16?frc=small")
    assert str(choice.with_options(post=False)) == "weier16?frc=small&post=false"
    assert choice.with_options(r1=12.0).params.frc == "small"
    with pytest.raises(ConfigError, match="p_min"):
        choice.with_options(p_min=2.0)
    with pytest.raises(ConfigError, match="unknown method 'magic'"):
        MethodChoice.parse("magic?x=1")
    with pytest.raises(ConfigError, match="must look like"):
        MethodChoice.parse("rrm?fovea_deg")


def test_weier16_renders_into_the_callers_buffer_as_into_its_own():
    scene = load_scene("interior")
    inputs = builtin_path(4, PROFILE.period_ns, scene.start, seed=3)
    own = run("weier16", "interior", lambda s: inputs)
    out = np.empty((PROFILE.height, PROFILE.width, 3), np.float32)
    with Whitted(scene) as tracer:
        method = make_method("weier16", tracer)
        for inp, (images, _) in zip(inputs, own, strict=True):
            cam = EyeCamera.for_eye(PROFILE, inp.pose, "left")
            assert method.render(FrameRequest(cam, inp.gaze["left"], inp.frame), FrameStats(), out) is out
            np.testing.assert_array_equal(out, images[0])
        with pytest.raises(ValueError, match="C-contiguous"):
            method.render(FrameRequest(cam, inp.gaze["left"], 5), FrameStats(), out[:, :-1])
