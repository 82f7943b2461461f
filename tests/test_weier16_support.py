"""weier16's support image against weier2016: a regular subset of the pixels, traced once each and merged into
the cache like any sample (sections 3.1, 3.4); what the mesh leaves uncovered taken from it rather than traced
(section 3.3); and a still view, which has no reprojection error to resample, refreshed at the foveal function's
rate plus the support image's (the resampled share each frame reported as resampled_fraction), at 192x216 and
640x720."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
import pytest

from hmdrt.foveation import FrameRequest, make_method
from hmdrt.foveation.stages.sampling import foveal_probability
from hmdrt.foveation.weier16 import Weier16, Weier16Params, support_size
from hmdrt.foveation.weier16.buffers import support_pixels
from hmdrt.foveation.weier16.cache import _unsampled_cells
from hmdrt.foveation.weier16.params import COVERED, RESAMPLE, SHOWN, SUPPORT, TRACED
from hmdrt.optics import get_profile
from hmdrt.optics.camera import eccentricity_map
from hmdrt.optics.projection import bilinear3
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose, gaze_direction, quat_multiply
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import FrameInput, eye_cameras, frame_requests

AHEAD = np.array(gaze_direction(0.0, 0.0))
WARMUP = 4  # frames before the still view is measured: the first has no history


class Recording:
    """The tracer, recording the sample positions of each call."""

    def __init__(self, tracer: Whitted):
        self.tracer, self.xy = tracer, []

    def __getattr__(self, name):
        return getattr(self.tracer, name)

    def trace_samples(self, camera, xy, *args, **kwargs):
        self.xy.append(xy.copy())
        return self.tracer.trace_samples(camera, xy, *args, **kwargs)


def request(width: int, height: int, frame: int, pose: Pose) -> FrameRequest:
    profile = get_profile("sim-cpu").with_resolution(width, height)
    inp = FrameInput(frame, frame * profile.period_ns, pose, {"left": AHEAD, "right": AHEAD})
    return frame_requests(inp, eye_cameras(profile, pose, ("left",)), 0)[0]


class Still(NamedTuple):
    """A still view of whitted, gaze ahead: each frame's flags, metrics and cache info, and the method."""

    flags: list[np.ndarray]
    metrics: list[dict]
    info: list[np.ndarray]
    samples: list[int]
    method: Weier16
    request: FrameRequest


def still(width: int, height: int, frames: int) -> Still:
    scene = load_scene("whitted")
    with Whitted(scene) as tracer:
        recording = Recording(tracer)
        method = Weier16(recording, Weier16Params())
        flags, metrics, info = [], [], []
        for f in range(frames):
            req = request(width, height, f, scene.start)
            stats = FrameStats()
            method.render(req, stats)
            eye = method._eyes["left"]
            flags.append(method._buffers.selection.flags.copy())
            metrics.append(dict(stats.metrics))
            info.append(eye.finals[eye.newest].info.copy())
    return Still(flags, metrics, info, [len(xy) for xy in recording.xy], method, req)


def foveal_share(req: FrameRequest, method: Weier16) -> np.ndarray:
    """Each pixel's probability of being traced by the foveal function, 1 in the fovea (section 3.1)."""
    fov = method.foveal
    ecc = eccentricity_map(req.camera, req.gaze)
    p = np.vectorize(lambda e: foveal_probability(e, fov.r0, fov.r1, fov.p_min))(ecc)
    return np.where(ecc < fov.r0, 1.0, np.minimum(p, 1.0))


def support_mask(width: int, height: int) -> np.ndarray:
    sw, sh = support_size(Weier16Params(), width, height)
    mask = np.zeros((height, width), bool)
    mask[np.ix_(support_pixels(height, sh), support_pixels(width, sw))] = True
    return mask


@pytest.fixture(scope="module")
def small():
    return still(192, 216, 10)


def test_support_pixels_are_pixels_traced_once(small):
    """Section 3.1: rays for the pixels that "belong to the support image's resolution", a regular subset of
    the pixels (floor((i + 0.5) w / sw)): each flagged SUPPORT and TRACED, and no sample beyond the traced pixels."""
    mask = support_mask(192, 216)
    sw, sh = support_size(Weier16Params(), 192, 216)
    assert mask.sum() == sw * sh
    for flags, n, metrics in zip(small.flags, small.samples, small.metrics, strict=True):
        np.testing.assert_array_equal((flags & SUPPORT) != 0, mask)
        assert ((flags[mask] & TRACED) != 0).all()
        assert n == ((flags & TRACED) != 0).sum()  # one ray per traced pixel: a support pixel is not traced twice
        assert metrics["sample_fraction"] == n / (192 * 216)
    grid = small.method._buffers.grid
    np.testing.assert_array_equal(grid.x, support_pixels(192, sw) + 0.5)  # the coarse mesh's vertices
    np.testing.assert_array_equal(grid.y, support_pixels(216, sh) + 0.5)


def test_the_support_image_is_its_pixels_samples(small):
    """The support image and G-buffer are extracted from the support pixels' samples (section 3.4): on whitted
    (no stochastic light) a pixel-centre sample is the full renderer's pixel."""
    with Whitted(load_scene("whitted")) as tracer:
        full = make_method("full", tracer).render(small.request, FrameStats())
    support = small.method._eyes["left"].support
    sw, sh = support_size(Weier16Params(), 192, 216)
    np.testing.assert_array_equal(support.color, full[np.ix_(support_pixels(216, sh), support_pixels(192, sw))])
    assert np.isfinite(support.depth).any() and (support.depth > 0).all()


def test_support_pixels_enter_the_cache(small):
    """A support pixel's sample updates its cache like any other (section 3.4): touched every frame, and outside
    the fovea merged by the running estimate, so its sample count grows."""
    mask = support_mask(192, 216)
    outside = mask & (foveal_share(small.request, small.method) < 1.0) & ((small.flags[-1] & COVERED) != 0)
    assert outside.sum() > 1000
    for f, info in enumerate(small.info):
        np.testing.assert_array_equal(info[mask, 2], f)  # t_touched
    assert (small.info[-1][outside, 1] > 3.0).mean() > 0.99  # rho: samples accumulated


def test_a_still_periphery_refreshes_at_p_min_plus_the_support_share(small):
    """Beyond r1 a still view traces each pixel with probability p_min (section 3.1) and every support pixel;
    the resampling info, with no reprojection error to find, adds next to nothing once the support image's
    reconstruction of the first frame has been tested (frame 2: its edges, once)."""
    method, req = small.method, small.request
    ecc = eccentricity_map(req.camera, req.gaze)
    beyond = ecc >= method.foveal.r1
    mask = support_mask(192, 216)[beyond]
    expected = mask.mean() + (1.0 - mask.mean()) * method.foveal.p_min
    rates, resampled = [], []
    for flags in small.flags[WARMUP:]:
        f = flags[beyond]
        rates.append(((f & (TRACED | RESAMPLE)) == TRACED).mean())
        resampled.append(((f & RESAMPLE) != 0).mean())
    # binomial spread of the p_min draws over these frames: about 0.0006
    assert abs(np.mean(rates) - expected) < 0.003, (np.mean(rates), expected)
    assert abs(expected - (method.foveal.p_min + mask.mean())) < 0.003  # "p_min + support share", the overlap small
    assert np.mean(resampled) < 0.003
    assert ((small.flags[2][beyond] & RESAMPLE) != 0).mean() > 0.1  # frame 0's support image, reprojected


@pytest.mark.parametrize(("width", "height"), [(192, 216), (640, 720)])
def test_a_still_view_traces_the_foveal_share_and_the_support_image(width, height, small):
    """After warm-up a still view traces what the foveal function and the support image ask, within 3 points
    (the resampling info finds no reprojection error there), at any resolution; resampled_fraction reports the
    share resampled."""
    run = small if width == 192 else still(width, height, 10)
    expected = np.maximum(foveal_share(run.request, run.method), support_mask(width, height)).mean()
    traced = [m["sample_fraction"] for m in run.metrics[WARMUP:]]
    assert abs(np.mean(traced) - expected) < 0.03, (np.mean(traced), expected)
    assert all(m["resampled_fraction"] == m["resampled_pixels"] / (width * height) for m in run.metrics)
    assert np.mean([m["resampled_fraction"] for m in run.metrics[WARMUP:]]) < 0.01


def test_uncovered_pixels_take_the_support_image_not_a_ray():
    """Section 3.3: what was outside the previous frustum and not traced by the foveal function is reconstructed
    from the support image (the merge), not marked in the resampling info."""
    scene = load_scene("whitted")
    turn = Pose(scene.start.position, quat_multiply(scene.start.orientation, Pose.looking((0, 0, 0), 8.0).orientation))
    with Whitted(scene) as tracer:
        method = Weier16(tracer, Weier16Params())
        method.render(request(96, 108, 0, scene.start), FrameStats())
        image = method.render(request(96, 108, 1, turn), FrameStats())
    buf, support = method._buffers, method._eyes["left"].support
    flags = buf.selection.flags
    low_uncovered = method._eyes["left"].low_mesh.image.zinv <= 0
    assert low_uncovered.sum() > 20  # the head turned 8 degrees: new cells at one side
    assert not buf.resample[low_uncovered].any()
    merged = (flags & (TRACED | COVERED)) == 0
    assert merged.sum() > 200
    ys, xs = np.nonzero(merged)
    expected = [bilinear3(support.color, buf.grid.u[x], buf.grid.v[y]) for y, x in zip(ys, xs, strict=True)]
    np.testing.assert_allclose(image[ys, xs], np.array(expected), rtol=1e-5, atol=1e-6)


def test_on_a_still_view_the_mesh_covers_everything_inside_the_support_grid(small):
    """The mesh's vertices sit on pixel centres on a still view, so its edges pass through pixel centres:
    none is left out of both triangles (the rasteriser's EDGE), so only the border outside the grid is merged."""
    grid = small.method._buffers.grid
    x0, x1, y0, y1 = int(grid.x[0]), int(grid.x[-1]), int(grid.y[0]), int(grid.y[-1])
    covered = (small.flags[-1] & COVERED) != 0
    inside = covered[y0 + 1 : y1, x0 + 1 : x1]  # the grid's outer edges pass through rays at infinity (sky)
    assert inside.all()


def test_the_cells_showing_the_support_image_are_those_holding_a_shown_pixel():
    """_unsampled_cells marks a cell (pixel (y, x) in cell (y sh // h, x sw // w)) where one of its pixels carries
    SHOWN, whatever other flags it or the others carry, and no other cell."""
    h, w, sh, sw = 10, 12, 3, 4
    flags = np.full((h, w), COVERED | TRACED | SUPPORT, np.uint8)
    flags[5, 7] = COVERED | SHOWN  # cell (1, 2)
    flags[9, 11] = COVERED
    unsampled = np.full((sh, sw), 7, np.uint8)
    _unsampled_cells(flags, unsampled, np.empty((nb.config.NUMBA_NUM_THREADS, w), np.uint8))
    expected = np.zeros((sh, sw), np.uint8)
    expected[1, 2] = 1
    np.testing.assert_array_equal(unsampled, expected)


def unsampled_by_definition(flags: np.ndarray, info: np.ndarray, sh: int, sw: int) -> np.ndarray:
    """Section 3.3's cells showing the support image, from the frame's flags and final cache info: those holding
    a covered pixel that was not traced and whose cache holds no sample (rho 0)."""
    h, w = flags.shape
    shown = ((flags & (COVERED | TRACED)) == COVERED) & (info[..., 1] <= 0.0)
    cells = np.zeros((sh, sw), np.uint8)
    ys, xs = np.nonzero(shown)
    cells[ys * sh // h, xs * sw // w] = 1
    return cells


def test_the_cache_update_flags_the_pixels_showing_the_support_image():
    """What the next frame's resampling info tests: after each frame of a still view and of a turning head, the
    cells the cache update reported (its SHOWN flags) are those the definition gives from its flags and cache
    info, and some are."""
    scene = load_scene("whitted")
    with Whitted(scene) as tracer:
        method = Weier16(tracer, Weier16Params())
        marked = 0
        for f in range(8):
            turn = Pose.looking((0, 0, 0), 1.5 * max(f - 4, 0)).orientation
            pose = Pose(scene.start.position, quat_multiply(scene.start.orientation, turn))
            method.render(request(192, 216, f, pose), FrameStats())
            eye = method._eyes["left"]
            unsampled = eye.support.unsampled
            flags, info = method._buffers.selection.flags, eye.finals[eye.newest].info
            np.testing.assert_array_equal(unsampled, unsampled_by_definition(flags, info, *unsampled.shape))
            marked += int(unsampled.sum())
    assert marked > 0
