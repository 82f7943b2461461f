"""weier16 against weier2016: the post filter of section 3.5 (donors, fovea, cache) and the resampling info of
section 3.3 (second-difference depth test, luminance of the reprojected final colour, cells tested where the
reprojection moved them), on `interior` and on hand-made buffers."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from hmdrt.evaluate.quality import psnr
from hmdrt.foveation import FrameRequest, Method, make_method
from hmdrt.foveation.stages.reproject import MeshImage
from hmdrt.foveation.weier16.buffers import Final, InfoRule, InfoScratch, PostRule, Samples, Selection, Surfaces
from hmdrt.foveation.weier16.params import COVERED, FOVEA, FRESH, RESAMPLE, TRACED
from hmdrt.foveation.weier16.post import _post
from hmdrt.foveation.weier16.resample import _resampling_info
from hmdrt.kernels.schedule import dynamic
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import eccentricity_map
from hmdrt.optics.projection import camera_arrays, view_distance
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import builtin_path, eye_cameras, frame_requests

PROFILE = get_profile("sim-cpu").with_resolution(96, 108)
FRAMES = 6
SCORED = slice(3, FRAMES)  # frames whose fovea is scored
R0 = 10.0  # the medium foveal region's r0, degrees


def requests(frames: int = FRAMES) -> list[FrameRequest]:
    """The left eye's requests along the built-in head path on `interior`."""
    scene = load_scene("interior")
    inputs = builtin_path(frames, PROFILE.period_ns, scene.start, seed=1)
    return [frame_requests(inp, eye_cameras(PROFILE, inp.pose, ("left",)), 0)[0] for inp in inputs]


def render(tracer: Whitted, spec: str, reqs: list[FrameRequest]) -> tuple[list[np.ndarray], Method]:
    """Every frame of `spec` along reqs, and the method (its state after the last frame)."""
    method = make_method(spec, tracer)
    return [method.render(r, FrameStats()).copy() for r in reqs], method


@pytest.fixture(scope="module")
def interior():
    """weier16 with and without the post filter, full, and 64-spp references of the scored frames."""
    reqs = requests()
    with Whitted(load_scene("interior")) as tracer:
        post, with_post = render(tracer, "weier16", reqs)
        plain, without = render(tracer, "weier16?post=false", reqs)
        full, _ = render(tracer, "full", reqs)
        reference = make_method("regular?spp=64", tracer)
        truths = [reference.render(r, FrameStats()).copy() for r in reqs[SCORED]]
    return reqs, post, plain, full, truths, with_post, without


def test_foveal_psnr_is_fulls(interior):
    """The fovea is traced afresh every frame (section 3.1), so its error against the reference is full's."""
    reqs, post, _, full, truths, *_ = interior
    fovea = np.stack([eccentricity_map(r.camera, r.gaze) < R0 for r in reqs[SCORED]])
    assert fovea.sum() > 500
    truth = np.stack(truths)
    ours, theirs = psnr(np.stack(post[SCORED]), truth, fovea), psnr(np.stack(full[SCORED]), truth, fovea)
    assert abs(ours - theirs) < 1.0, f"fovea: weier16 {ours:.2f} dB, full {theirs:.2f} dB"


def test_no_post_filter_inside_the_fovea(interior):
    """Section 3.5 evens out resampled against reconstructed regions; in the fovea every pixel is resampled."""
    _, post, plain, _, _, with_post, _ = interior
    flags = with_post._buffers.selection.flags
    fovea = (flags & FOVEA) != 0
    assert ((flags & RESAMPLE) != 0)[fovea].any()  # there are resampled pixels the filter could have taken
    np.testing.assert_array_equal(post[-1][fovea], plain[-1][fovea])
    assert not np.array_equal(post[-1], plain[-1])  # it does run outside


def test_the_cache_keeps_the_colour_before_the_post_filter(interior):
    """The post filter changes the image shown, never what the next frame reprojects."""
    *_, with_post, without = interior
    for a, b in zip(with_post._eyes["left"].finals, without._eyes["left"].finals, strict=True):
        for name in Final._fields:
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


def test_merged_pixels_carry_the_support_images_light_buffer():
    """Pixels merged from the support image (section 3.4) hold its light buffer, not zero: a reconstructed pixel
    that later lends its light (section 3.5) lends a lit surface's."""
    (request,) = requests(1)
    with Whitted(load_scene("interior")) as tracer:
        _, method = render(tracer, "weier16", [request])  # no history: every untraced pixel is merged
    merged = (method._buffers.selection.flags & TRACED) == 0
    final = method._eyes["left"].finals[method._eyes["left"].newest]
    assert merged.mean() > 0.5
    assert (final.light[merged].max(axis=-1) > 0.0).mean() > 0.99


def test_a_merged_pixel_counts_no_sample_and_its_next_sample_replaces_it():
    """rho is the number of samples accumulated at a pixel (section 3.4); the support image's bilinear colour
    is none of them, so the first sample on a merged pixel's reprojected cache takes alpha = 1."""
    reqs = requests(2)
    with Whitted(load_scene("interior")) as tracer:
        method = make_method("weier16", tracer)
        method.render(reqs[0], FrameStats())
        merged = (method._buffers.selection.flags & TRACED) == 0
        method.render(reqs[1], FrameStats())
    flags = method._buffers.selection.flags
    prev = method._eyes["left"].mesh.image.prev  # the cache info comes from the nearest texel
    h, w = flags.shape
    # where the mesh covers no pixel its coordinates are not finite or far off, and the flags below say so
    prev = np.clip(np.nan_to_num(prev, nan=0.0), 0, [[[w - 1]], [[h - 1]]]).astype(int)
    came_from = merged[prev[1], prev[0]]
    again = came_from & ((flags & (TRACED | FRESH | COVERED)) == (TRACED | COVERED))
    info = method._eyes["left"].finals[method._eyes["left"].newest].info
    assert again.sum() > 50
    np.testing.assert_array_equal(info[again, 0], 1.0)  # alpha
    np.testing.assert_array_equal(info[again, 1], 1.0)  # rho


# -- section 3.5's donors on hand-made buffers: a plane facing the eye 2 m ahead --

SIZE, CENTRE = 11, 5
GOOD, BAD, ALBEDO, OWN = 0.6, 9.0, 0.5, 0.2  # light buffers: donors', wrong ones', the pixel's own sample


def plane_camera() -> EyeCamera:
    return EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(SIZE, SIZE), Pose())


def post_buffers(cam: EyeCamera):
    """Every pixel traced once and merged into its cache on the plane, lending GOOD; the centre resampled with
    its own sample OWN; around it, at distance 1, eight pixels that must not lend: each breaks one condition."""
    n, cur = SIZE * SIZE, camera_arrays(cam)
    ys, xs = np.divmod(np.arange(n), SIZE)
    depth = np.array([view_distance(cur, x + 0.5, y + 0.5, 2.0) for y, x in zip(ys, xs, strict=True)], np.float32)
    normal = np.tile(np.float32([0.0, 0.0, 1.0]), (n, 1))
    flags = np.full((SIZE, SIZE), TRACED | COVERED, np.uint8)
    final = Final(
        np.zeros((SIZE, SIZE, 3), np.float32),
        np.ones((SIZE, SIZE, 3), np.float32),
        np.full((SIZE, SIZE, 3), GOOD, np.float32),
    )
    final.info[..., 1] = 4.0  # rho: samples accumulated
    c = CENTRE
    flags[c, c] = TRACED | FRESH | RESAMPLE | COVERED
    flags[c, c + 1] = COVERED  # reprojected, not traced this frame
    final.info[c, c - 1, 1] = 1.0  # traced, but its cache restarted: one sample
    flags[c + 1, c] = TRACED | FRESH | COVERED  # traced afresh (fovea or moved): one sample
    flags[c - 1, c] = 0  # merged from the support image
    for dy, dx in ((-1, -1), (1, 1)):  # another surface: 2.5 m away
        k = (c + dy) * SIZE + c + dx
        depth[k] = view_distance(cur, c + dx + 0.5, c + dy + 0.5, 2.5)
    for dy, dx in ((-1, 1), (1, -1)):  # another surface: at right angles
        normal[(c + dy) * SIZE + c + dx] = (1.0, 0.0, 0.0)
    for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0), (-1, -1), (1, 1), (-1, 1), (1, -1)):
        final.light[c + dy, c + dx] = BAD
    light = np.full((n, 3), OWN, np.float32)
    albedo = np.full((n, 3), ALBEDO, np.float32)
    samples = Samples(albedo * light, depth, light, albedo)
    rows = np.full(SIZE, SIZE, np.int64)
    selection = Selection(flags, rows, np.arange(SIZE + 1, dtype=np.int64) * SIZE, rows.copy(), rows * 0)
    surfaces = Surfaces(np.arange(n, dtype=np.int32).reshape(SIZE, SIZE), depth, normal)
    return selection, surfaces, samples, final


def run_post(selection, surfaces, samples, final, cam, seed: int = 0) -> np.ndarray:
    image = samples.rgb.reshape(SIZE, SIZE, 3).copy()
    dynamic(_post, selection, surfaces, samples, final, camera_arrays(cam), PostRule(32, 8, seed, 0.02, 0.9), image)
    return image


@pytest.mark.parametrize("seed", range(4))
def test_donors_are_traced_accumulated_and_on_the_pixels_surface(seed):
    """Section 3.5 borrows a reconstructed pixel's light buffer: one traced this frame, merged into its cache,
    on the same surface; none of the eight nearer pixels that fail one of those lends."""
    cam = plane_camera()
    selection, surfaces, samples, final = post_buffers(cam)
    before = final.color.copy()
    image = run_post(selection, surfaces, samples, final, cam, seed)
    np.testing.assert_allclose(image[CENTRE, CENTRE], ALBEDO * GOOD, rtol=1e-6)
    image[CENTRE, CENTRE] = ALBEDO * OWN
    np.testing.assert_array_equal(image, samples.rgb.reshape(SIZE, SIZE, 3))  # only the resampled pixel changed
    np.testing.assert_array_equal(final.color, before)  # nor the cache


def test_no_donor_no_change_and_the_fovea_is_left_alone():
    cam = plane_camera()
    selection, surfaces, samples, final = post_buffers(cam)
    final.info[..., 1] = 1.0  # no pixel holds more than one sample
    assert (run_post(selection, surfaces, samples, final, cam) == ALBEDO * OWN).all()
    selection, surfaces, samples, final = post_buffers(cam)
    selection.flags[CENTRE, CENTRE] |= FOVEA
    assert (run_post(selection, surfaces, samples, final, cam) == ALBEDO * OWN).all()


# -- section 3.3's resampling info on a hand-made reprojection at the support resolution --

SW, FULL = 16, 64  # support cells and full-resolution pixels per side


def previous_positions(shift: float = 1.0) -> np.ndarray:
    """Where each cell's surface lay in the previous frame for a view that pans by `shift` full-resolution pixels
    (each cell sees the previous texels that far to its left; 0: a still view), (2, SW, SW) x and y."""
    centres = (np.arange(SW) + 0.5) * FULL / SW
    return np.stack(np.broadcast_arrays(centres[None, :] - shift, centres[:, None])).astype(np.float32)


def info_marks(
    zinv: np.ndarray,
    color: np.ndarray,
    prev: np.ndarray | None = None,
    motion: float = 0.1,
    unsampled: np.ndarray | None = None,
) -> np.ndarray:
    """The cells marked for depths 1/zinv and final colour `color` reprojected from `prev` (a pan by one pixel
    by default), no normals (no grazing test), cells tested where they or a neighbour moved more than `motion`
    or where the previous frame showed the support image's reconstruction (`unsampled`, none by default)."""
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(FULL, FULL), Pose())
    scratch = InfoScratch(
        np.empty((SW, SW), np.uint8),
        np.empty((SW, SW), np.uint8),
        np.empty((SW, SW), np.float32),
        np.empty((numba.config.NUMBA_NUM_THREADS, FULL), np.float32),
    )
    out = np.empty((SW, SW), bool)
    _resampling_info(
        MeshImage(previous_positions() if prev is None else prev, zinv.astype(np.float32)),
        camera_arrays(cam, SW, SW),
        color.astype(np.float32),
        np.zeros((SW, SW, 3), np.float32),
        np.zeros((SW, SW), np.uint8) if unsampled is None else unsampled,
        np.zeros(3),
        float(FULL),
        float(FULL),
        InfoRule(0.05, 0.2, 0.1, motion, np.random.default_rng(0).standard_normal((4, 2))),
        scratch,
        out,
    )
    return out


def slanted_plane() -> np.ndarray:
    """1/z of a plane slanted so steeply that neighbouring cells' depths differ by 5.5-40%."""
    return np.broadcast_to(0.1 + 0.04 * np.arange(SW) + 0.002 * np.arange(SW)[:, None], (SW, SW)).copy()


def test_the_depth_test_marks_a_step_but_not_a_slanted_plane():
    """Section 3.3: a depth difference between a cell and its direct neighbourhood. On a plane 1/z is affine in
    the image, and the coarse mesh reprojects it exactly: a second difference leaves it unmarked where a first
    difference would mark every cell."""
    zinv, grey = slanted_plane(), np.full((FULL, FULL, 3), 0.5)
    depth = 1.0 / zinv
    assert (np.abs(np.diff(depth, axis=1)) > 0.05 * depth[:, 1:]).all()  # a first difference marks it all
    assert not info_marks(zinv, grey).any()
    zinv[:, SW // 2 :] += 0.3  # a box in front of the right half
    marks = info_marks(zinv, grey)
    assert marks[:, SW // 2 - 1 : SW // 2 + 1].all()
    marks[:, SW // 2 - 1 : SW // 2 + 1] = False
    assert not marks.any()


def test_the_luminance_test_reads_the_reprojected_final_colour():
    """The luminance contrast is taken on the previous frame's final colour seen through the mesh: a bright
    right half of that image marks the cells at its edge, and only those."""
    color = np.full((FULL, FULL, 3), 0.1)
    color[:, FULL // 2 :] = 0.9
    marks = info_marks(slanted_plane(), color)
    assert marks[:, SW // 2 - 1 : SW // 2 + 1].all()
    marks[:, SW // 2 - 2 : SW // 2 + 2] = False  # the footprint filter may reach one cell further
    assert not marks.any()


def step_and_edge() -> tuple[np.ndarray, np.ndarray]:
    """A box in front of the right half of a slanted plane, bright on the bottom half of the image."""
    zinv, color = slanted_plane(), np.full((FULL, FULL, 3), 0.1)
    zinv[:, SW // 2 :] += 0.3
    color[FULL // 2 :] = 0.9
    return zinv, color


def test_a_still_view_marks_nothing():
    """Section 3.3 looks for reprojection errors; a still view reprojects the previous frame onto itself, so its
    depth steps and contrast edges, marked once the view moves, are left to the cache."""
    zinv, color = step_and_edge()
    assert not info_marks(zinv, color, previous_positions(0.0)).any()
    assert not info_marks(zinv, color, previous_positions(0.09), motion=0.1).any()
    moved = info_marks(zinv, color, previous_positions(0.11), motion=0.1)
    assert moved[:, SW // 2 - 1 : SW // 2 + 1].all() and moved[SW // 2 - 1 : SW // 2 + 1].all()


def test_a_cell_next_to_a_moved_one_is_tested():
    """The tests read a cell's 4-neighbours: a cell that stayed still beside one that moved is tested too."""
    zinv, color = step_and_edge()
    prev = previous_positions(0.0)
    prev[0, :, SW // 2] -= 1.0  # only the box's first column moved
    marks = info_marks(zinv, color, prev)
    assert marks[:, SW // 2 - 1 : SW // 2 + 1].all()  # the step, on both sides
    assert not marks[:, : SW // 2 - 2].any() and not marks[:, SW // 2 + 2 :].any()  # the edge away from the move


def test_a_still_cell_showing_the_support_image_is_tested():
    """Section 3.3 reconstructs pixels outside the previous frustum from the coarse support image; where the
    reprojection shows such pixels (no sample of their own yet), their cells are tested like moved ones."""
    zinv, color = step_and_edge()
    unsampled = np.zeros((SW, SW), np.uint8)
    unsampled[: SW // 4] = 1  # the top quarter showed the support image
    marks = info_marks(zinv, color, previous_positions(0.0), unsampled=unsampled)
    assert marks[: SW // 4, SW // 2 - 1 : SW // 2 + 1].all()  # the step, there
    assert not marks[SW // 4 :].any()
