"""The shared reconstruction stages against hand-computed values: mesh and back-projection, pull-push, the
pyramid's taps, contrast windows, the light buffer and weier18's TAA (the sampling and filter formulas:
test_stages.py)."""

import numpy as np
import pytest

from hmdrt.foveation.stages import reproject as rp
from hmdrt.foveation.stages.dof import (
    Blur,
    combine,
)
from hmdrt.foveation.stages.filters import FINE_LEVELS, Contrast, contrast_levels, enhance_windows, prefilter
from hmdrt.foveation.stages.pyramid import (
    DEPTH,
    WEIGHT,
    LevelSamples,
    Pyramid,
    RowSamples,
    _axis,
    _pull_level,
    _pull_samples,
    pixel_axes,
    pull_push,
    push_columns,
    sample_row,
)
from hmdrt.foveation.stages.reproject import CoarseMesh, backproject
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.optics.projection import FAR
from hmdrt.scene import Scene
from hmdrt.scene.model import AreaLight, Material
from hmdrt.scene.shapes import quad, sphere
from hmdrt.spatial import Pose, gaze_direction
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.gbuffer import LightBuffer
from hmdrt.trace.integrator import Whitted


def camera(profile="rift_s", pose=None, width=None, height=None):
    p = get_profile(profile)
    if width:
        p = p.with_resolution(width, height)
    return EyeCamera.for_eye(p, pose or Pose.looking((0.0, 1.6, 0.0)))


# -- weier2016 section 3.4: running estimate and k(dt) --
# -- reprojection and reconstruction --


def test_mesh_reprojection_is_exact_for_an_unmoved_camera():
    cam = camera("sim-cpu", width=96, height=108)
    sw, sh = 24, 27
    gx, gy = (np.arange(sw) + 0.5) * 96 / sw, (np.arange(sh) + 0.5) * 108 / sh
    depth = 2.0 + np.random.default_rng(0).random((sh, sw))
    mesh, zinv = CoarseMesh().reproject(cam, gx, gy, depth, cam, 96, 108)
    inner = np.zeros((108, 96), bool)
    inner[4:-4, 2:-2] = True
    covered = (zinv > 0) & inner
    assert covered.sum() > 0.95 * inner.sum()
    ys, xs = np.nonzero(covered)
    np.testing.assert_allclose(mesh[0, ys, xs], xs + 0.5, atol=1e-3)
    np.testing.assert_allclose(mesh[1, ys, xs], ys + 0.5, atol=1e-3)


def test_mesh_and_back_projection_agree_after_a_head_turn():
    before = camera("sim-cpu", Pose.looking((0.0, 1.6, 0.0), 0.0, 0.0), 96, 108)
    after = camera("sim-cpu", Pose.looking((0.05, 1.6, 0.0), 4.0, 1.0), 96, 108)
    sw, sh = 48, 54
    gx, gy = (np.arange(sw) + 0.5) * 2, (np.arange(sh) + 0.5) * 2
    depth = np.full((sh, sw), 3.0)  # a sphere of radius 3 around the first eye
    mesh, zinv = CoarseMesh().reproject(before, gx, gy, depth, after, 96, 108)
    # the surface seen at a pixel lies on its view ray at view depth 1 / zinv: back-projected from the new camera
    # into the old one, it lands where it came from
    tx = after.tan_left + (np.arange(96) + 0.5) * (after.tan_right - after.tan_left) / 96
    ty = after.tan_up - (np.arange(108) + 0.5) * (after.tan_up - after.tan_down) / 108
    with np.errstate(divide="ignore"):
        dist = np.sqrt(tx[None, :] ** 2 + ty[:, None] ** 2 + 1.0) / zinv
    xy, dist_before = backproject(after, np.where(zinv > 0, dist, np.inf).astype(np.float32), before)
    ok = (zinv > 0) & np.isfinite(xy[..., 0])
    assert ok.sum() > 5000
    np.testing.assert_allclose(xy[ok], np.moveaxis(mesh, 0, -1)[ok], atol=2e-2)
    np.testing.assert_allclose(dist_before[ok], 3.0, rtol=2e-3)  # on the chords of the sphere of radius 3


def _reference_raster(screen, attr, width, height, near):
    """weier2016 section 3.2's rasterisation written plainly: every triangle of every grid cell in the mesh's order,
    culled at the near plane, each pixel centre inside it (its weights above 1e-6) blended in where its 1/z beats
    what the pixel holds; and the centres within 1e-6 of an edge, where the rounding decides, to leave out."""
    prev, zinv = np.zeros((2, height, width)), np.zeros((height, width))
    edge = np.zeros((height, width), bool)
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    hs, ws = screen.shape[:2]
    for j in range(hs - 1):
        for i in range(ws - 1):
            for a, b, c in (((j, i), (j, i + 1), (j + 1, i + 1)), ((j, i), (j + 1, i + 1), (j + 1, i))):
                (ax, ay, az), (bx, by, bz), (cx, cy, cz) = screen[a], screen[b], screen[c]
                area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
                if min(az, bz, cz) <= near or abs(area) < 1e-12:
                    continue
                wa = ((bx - xs) * (cy - ys) - (by - ys) * (cx - xs)) / area
                wb = ((cx - xs) * (ay - ys) - (cy - ys) * (ax - xs)) / area
                wc = 1.0 - wa - wb
                low = np.minimum(np.minimum(wa, wb), wc)
                edge |= np.abs(low) < 1e-6
                iz = wa * attr[a][3] + wb * attr[b][3] + wc * attr[c][3]
                win = (low > 1e-6) & (iz > zinv)
                zp = wa * attr[a][2] + wb * attr[b][2] + wc * attr[c][2]
                for k in range(2):
                    prev[k][win] = ((wa * attr[a][k] + wb * attr[b][k] + wc * attr[c][k]) / zp)[win]
                zinv[win] = iz[win]
    return prev, zinv, edge


@pytest.mark.parametrize(
    "pose",
    [((0.1, 1.6, -0.3), 10.0, -6.0), ((0.0, 1.4, -0.25), 0.0, 10.0)],
    ids=["cells-culled-whole-or-half", "cells-folded-over-themselves"],
)
def test_mesh_raster_matches_every_triangle_drawn_in_order_with_a_depth_test(pose):
    """Folds in the mesh (a near block before a far wall, seen after a step) overlap triangles, those of one cell
    among them, and vertices behind the eye cull theirs: each pixel away from an edge holds the nearest triangle
    that covers it."""
    before = camera("sim-cpu", Pose.looking((0.0, 1.6, 0.0), 0.0, 0.0), 96, 108)
    after = camera("sim-cpu", Pose.looking(*pose), 96, 108)
    sw, sh = 24, 27
    gx, gy = (np.arange(sw) + 0.5) * 4, (np.arange(sh) + 0.5) * 4
    rng = np.random.default_rng(3)
    depth = 4.0 + rng.random((sh, sw))
    depth[8:18, 6:14] = 0.7 + 0.1 * rng.random((10, 8))  # a near block: its sides stretch into folds
    # behind the new eye after its step forward: their triangles culled, both of a cell's or one
    depth[:, :2] = depth[4, 16] = depth[20, 18] = 0.25
    vertices = rp.GridProjection().project(rp.SupportGrid(before, gx, gy, depth, after), (96, 108))
    assert (vertices.screen[..., 2] <= rp.NEAR).any()
    mesh, zinv = CoarseMesh().reproject(before, gx, gy, depth, after, 96, 108)
    prev, ref, edge = _reference_raster(vertices.screen, vertices.attr, 96, 108, rp.NEAR)
    away = ~edge
    assert (ref[away] > 0).sum() > 5000 and (ref[away] == 0).sum() > 1000
    np.testing.assert_array_equal(zinv[away] > 0, ref[away] > 0)
    inside = away & (ref > 0)
    np.testing.assert_allclose(zinv[inside], ref[inside], rtol=1e-6)
    np.testing.assert_allclose(mesh[:, inside], prev[:, inside], atol=1e-3)


def test_meshes_of_one_projection_match_meshes_of_their_own_and_project_once_per_change():
    """weier16's two meshes (full and support resolution) share one projection of the grid: each image the same bits
    as a mesh projecting for itself, the vertices projected once per change of the inputs, none on a still view."""
    before = camera("sim-cpu", Pose.looking((0.0, 1.6, 0.0), 0.0, 0.0), 96, 108)
    after = camera("sim-cpu", Pose.looking((0.03, 1.6, -0.02), 3.0, -1.0), 96, 108)
    sw, sh = 24, 27
    gx, gy = (np.arange(sw) + 0.5) * 4, (np.arange(sh) + 0.5) * 4
    depth = 2.0 + np.random.default_rng(5).random((sh, sw))
    projection = rp.GridProjection()
    full, low = CoarseMesh(projection), CoarseMesh(projection)
    moves = []
    for cur in (after, before, before):
        versions = projection.version
        shared = [m.reproject(before, gx, gy, depth, cur, w, h) for m, (w, h) in ((full, (96, 108)), (low, (sw, sh)))]
        own = [CoarseMesh().reproject(before, gx, gy, depth, cur, w, h) for w, h in ((96, 108), (sw, sh))]
        for a, b in zip(shared, own, strict=True):
            covered = a.zinv > 0  # the mesh image's coordinates where it covers a pixel
            assert covered.any()
            np.testing.assert_array_equal(a.zinv.view(np.uint32), b.zinv.view(np.uint32))
            np.testing.assert_array_equal(a.prev[:, covered].view(np.uint32), b.prev[:, covered].view(np.uint32))
        moves.append(projection.version - versions)
    assert moves == [2, 1, 0]  # the first call meets the sizes one at a time; a still view projects nothing
    assert full.still and low.image.zinv.shape == (sh, sw)


def test_pull_push_keeps_samples_and_fills_holes():
    rng = np.random.default_rng(1)
    h, w = 37, 50
    truth = np.stack(np.meshgrid(np.linspace(0, 1, w), np.linspace(0, 1, h)), -1).mean(-1)
    pyr = Pyramid.empty(w, h)
    level0 = pyr.data[: w * h]
    chosen = np.flatnonzero(rng.random(w * h) < 0.15)
    level0[chosen, :3] = truth.reshape(-1)[chosen, None]
    level0[chosen, WEIGHT] = 1.0
    level0[chosen, DEPTH] = 2.0
    pull_push(pyr)
    dense = pyr.level(0)
    np.testing.assert_allclose(dense[..., 0].reshape(-1)[chosen], truth.reshape(-1)[chosen], atol=1e-6)
    assert np.all(dense[..., WEIGHT] == 1.0)
    assert np.abs(dense[..., 0] - truth).max() < 0.15  # a smooth ramp is reconstructed closely
    np.testing.assert_allclose(dense[..., DEPTH], 2.0, atol=1e-6)


def listed(pyr: Pyramid, mask: np.ndarray) -> LevelSamples:
    """Level 0's texels under mask (height, width) as a sample list, their colour and depth copied out."""
    fine = pyr.level(0)
    texels = np.flatnonzero(mask)
    starts = np.concatenate([[0], np.cumsum(mask.sum(1))]).astype(np.int64)
    rgb, depth = fine.reshape(-1, 5)[texels, :3].copy(), fine.reshape(-1, 5)[texels, DEPTH].copy()
    return LevelSamples(mask.reshape(-1), texels, starts, rgb, depth)


@pytest.mark.parametrize("masked", [False, True])
def test_pull_averages_the_valid_children_and_ignores_what_zero_weights_hold(masked):
    """Each texel of level 1 is the weighted mean of its valid children (fractional weights, or a sample list's 1
    and 0; odd sizes, so the last row and column have fewer children), its weight their sum capped at 1; a child of
    weight 0 counts for nothing, not even the NaN it may hold."""
    rng = np.random.default_rng(3)
    w, h = 37, 23
    pyr = Pyramid.empty(w, h)
    fine = pyr.level(0)
    fine[...] = rng.random(fine.shape, np.float32)
    weights = np.where(rng.random((h, w)) < 0.5, 0.0, rng.random((h, w))).astype(np.float32)
    mask = weights > 0
    if masked:
        weights = mask.astype(np.float32)
        fine[..., WEIGHT] = np.nan  # the weight channel is not read
    else:
        fine[..., WEIGHT] = weights
    fine[~mask, :3], fine[~mask, DEPTH] = np.nan, np.nan
    if masked:
        _pull_samples(pyr, listed(pyr, mask), push_columns(w).sums)
    else:
        _pull_level(pyr, 1)
    coarse = pyr.level(1)
    for y in range(coarse.shape[0]):
        for x in range(coarse.shape[1]):
            block = fine[2 * y : 2 * y + 2, 2 * x : 2 * x + 2].reshape(-1, 5)
            wts = weights[2 * y : 2 * y + 2, 2 * x : 2 * x + 2].reshape(-1)
            valid = wts > 0
            total = float(wts[valid].sum())
            assert coarse[y, x, WEIGHT] == pytest.approx(min(1.0, total))
            if total > 0:
                expected = (wts[valid, None] * block[valid][:, :4]).sum(0) / total
                np.testing.assert_allclose(coarse[y, x, :4], expected, rtol=1e-5)


def test_pull_push_from_a_sample_list_gives_the_bits_of_level_0_with_those_weights():
    """A pull-push that takes level 0's samples from a list (the weier18 frame's) fills the pyramid as one that reads
    level 0 with weight 1 at the samples and 0 elsewhere, bit for bit, whatever level 0 held: it writes the samples
    into their texels itself."""
    rng = np.random.default_rng(4)
    w, h = 51, 37
    listed_pyr, weighted = Pyramid.empty(w, h), Pyramid.empty(w, h)
    listed_pyr.data[...] = rng.random(listed_pyr.data.shape, np.float32)
    mask = rng.random((h, w)) < 0.2
    mask[10:20, 15:30] = True  # a dense patch, as the fovea is
    weighted.data[...] = listed_pyr.data
    weighted.data[: w * h, WEIGHT] = mask.reshape(-1)
    samples = listed(listed_pyr, mask)
    listed_pyr.data[: w * h] = np.nan  # level 0's texels are not read: the samples come from the list
    pull_push(listed_pyr, samples)
    pull_push(weighted)
    np.testing.assert_array_equal(listed_pyr.data, weighted.data)


def test_pull_push_of_a_one_texel_image_places_its_sample():
    """A 1x1 image's pyramid has no coarser level to pull into or push from: its sample still lands in its texel."""
    pyr = Pyramid.empty(1, 1)
    pyr.data[...] = np.nan
    samples = LevelSamples(
        np.ones(1, bool), np.zeros(1, np.int64), np.array([0, 1]), np.array([[0.25, 0.5, 0.75]], np.float32),
        np.array([3.0], np.float32),
    )  # fmt: skip
    pull_push(pyr, samples)
    np.testing.assert_array_equal(pyr.data, [[0.25, 0.5, 0.75, 3.0, 1.0]])


def test_pull_push_with_kept_columns_matches_and_refuses_short_ones():
    rng = np.random.default_rng(2)
    a, b = Pyramid.empty(50, 37), Pyramid.empty(50, 37)
    chosen = np.flatnonzero(rng.random(50 * 37) < 0.2)
    colours = rng.random((len(chosen), 3), dtype=np.float32)
    for pyr in (a, b):
        pyr.data[chosen, :3], pyr.data[chosen, WEIGHT] = colours, 1.0
    pull_push(a)
    pull_push(b, columns=push_columns(64))  # wider scratch than level 0: only its first 50 entries are used
    np.testing.assert_array_equal(a.data, b.data)
    with pytest.raises(ValueError, match="columns hold 49 texels, level 0 has 50"):
        pull_push(b, columns=push_columns(49))


def test_pixel_axes_hold_each_pixel_centres_taps_on_every_level():
    """The tables sample_pixel reads agree with the per-pixel computation (_axis) they replace, on a size whose
    levels halve unevenly."""
    w, h = 37, 23
    pyr = Pyramid.empty(w, h)
    axes = pixel_axes(pyr)
    for k in range(len(pyr.offsets)):
        first, width = int(pyr.offsets[k]), int(pyr.widths[k])
        for x in range(w):
            i0, i1, a = _axis((x + 0.5) * pyr.scale_x[k], pyr.widths[k])
            assert (axes.col0[k, x], axes.col1[k, x], axes.col_weight[k, x]) == (i0, i1, a)
        for y in range(h):
            j0, j1, b = _axis((y + 0.5) * pyr.scale_y[k], pyr.heights[k])
            assert (axes.row0[k, y], axes.row1[k, y]) == (first + j0 * width, first + j1 * width)
            assert axes.row_weight[k, y] == b


def _trilinear(pyr, level, x, y):
    """Colour at pixel (x, y)'s centre on a fractional level, from the per-pixel _axis."""

    def tap(k):
        i0, i1, a = _axis((x + 0.5) * pyr.scale_x[k], pyr.widths[k])
        j0, j1, b = _axis((y + 0.5) * pyr.scale_y[k], pyr.heights[k])
        texel = pyr.level(k)[:, :, :3].astype(np.float64)
        a, b = float(a), float(b)
        top = (1 - a) * texel[int(j0), int(i0)] + a * texel[int(j0), int(i1)]
        bottom = (1 - a) * texel[int(j1), int(i0)] + a * texel[int(j1), int(i1)]
        return (1 - b) * top + b * bottom

    top = len(pyr.offsets) - 1
    level = min(level, top)
    k = int(level)
    return tap(k) if k == top else tap(k) + (level - k) * (tap(k + 1) - tap(k))


def test_sample_row_reads_every_pixels_own_level_and_leaves_the_unselected():
    """One pass per level over a row holding levels 0, fractional, integer, the top and beyond it; pixels
    with a negative level keep what their values held."""
    w, h = 37, 23
    pyr = Pyramid.empty(w, h)
    pyr.data[:] = np.random.default_rng(5).random(pyr.data.shape, np.float32)
    top = len(pyr.offsets) - 1
    levels = np.array([0.0, 0.25, 1.0, 1.5, 2.75, -1.0, top, top + 3.0, 0.9] * 5)[:w]
    scratch = RowSamples.empty(w)
    values = scratch.values[0]
    values[:] = 7.0
    y = 9
    sample_row(pyr.data, pyr.widths, pixel_axes(pyr), y, levels, values, scratch.texels[0], scratch.runs[0])
    for x, level in enumerate(levels):
        expected = np.full(3, 7.0) if level < 0 else _trilinear(pyr, level, x, y)
        np.testing.assert_allclose(values[x], expected, rtol=1e-5, atol=1e-6, err_msg=f"x={x} level={level}")


def test_enhance_windows_cover_every_texel_the_contrast_reads():
    """The contrast enhancement over a pyramid prefiltered only inside enhance_windows (NaN elsewhere) equals
    the one over the whole prefiltered pyramid, with the gaze off-centre; the finest level's window is a small
    part of that level."""
    cam = camera(width=256, height=288)
    ecc = np.asarray(cam.eccentricity(gaze_direction(12, -6)), np.float32)
    pyr = Pyramid.empty(256, 288)
    pyr.data[:] = np.random.default_rng(2).random(pyr.data.shape, np.float32)
    levels = contrast_levels(ecc, 10.0, np.empty(ecc.shape, np.float32))
    contrast = Contrast(0.2, 10.0, 20.0, levels)
    windows = enhance_windows(ecc, contrast, pyr, np.empty((288, FINE_LEVELS, 2), np.int64))
    whole, windowed = Pyramid.empty(256, 288), Pyramid.empty(256, 288)
    windowed.data[:] = np.nan
    prefilter(pyr, whole)
    prefilter(pyr, windowed, windows)
    axes, color = pixel_axes(pyr), pyr.level(0)[..., :3]
    images = [
        combine(
            color,
            ecc,
            None,
            Blur(10.0, 20.0),
            pyr,
            contrast,
            blurred,
            axes,
            RowSamples.empty(256),
            np.empty_like(color),
        )
        for blurred in (whole, windowed)
    ]
    assert np.isfinite(images[1]).all()
    np.testing.assert_array_equal(images[0], images[1])
    x0, x1, y0, y1 = windows[0]
    assert 0 < (x1 - x0) * (y1 - y0) < 0.25 * 256 * 288
    assert (windows[2:, 0] == 0).all() and (windows[2:, 1] == pyr.widths[2:]).all()


# -- the light buffer behind weier2016's post-process --


def test_light_buffer_is_the_stochastic_part_of_the_colour():
    mats = {"m": Material(diffuse=(0.6, 0.5, 0.4))}
    scene = Scene(
        "box",
        [quad("floor", (-3, 0, 3), (6, 0, 0), (0, 0, -6), "m"), sphere("s", (0, 0.5, -2), 0.5, "m")],
        mats,
        [AreaLight(corner=(-0.5, 2.5, -2.5), edge_u=(0, 0, 1), edge_v=(1, 0, 0), radiance=(4, 4, 4))],
        ambient=(0.3, 0.3, 0.3),
        ao_samples=4,
        max_depth=0,
        start=Pose.looking((0, 1.5, 1.0), 0, -30),
    )
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(32, 32), scene.start)
    with Whitted(scene) as tracer:
        xy = pixel_centres(32, 32)
        light = LightBuffer.empty(len(xy))
        rgb = tracer.trace_samples(cam, xy, np.arange(len(xy)), FrameStats(), light=light)
    np.testing.assert_allclose(rgb, light.albedo * light.irradiance, atol=1e-5)  # no emission, no specular
    assert light.irradiance.max() > 0


@pytest.mark.parametrize("previous_depth", [2.0, FAR])
def test_weier18_taa_blends_each_sample_only_with_taps_that_see_its_surface(previous_depth):
    """weier2018 section 3.1's TAA on a still view: a sample on a surface blends with the previous frame's taps at
    its distance, a miss only with taps that missed too; all five taps seen, the new sample keeps alpha_min."""
    from hmdrt.foveation.stages.pyramid import quincunx_offset
    from hmdrt.foveation.stages.temporal import relative_view
    from hmdrt.foveation.weier18 import Blend, Reprojected, Tangents, Traced, _taa

    w, h = 16, 12
    cam = camera("sim-cpu", width=w, height=h)
    previous = Pyramid.empty(w, h)
    previous.data[:, :3] = (1.0, 0.0, 0.0)
    previous.data[:, WEIGHT], previous.data[:, DEPTH] = 1.0, previous_depth
    surface, miss = 5 * w + 5, 6 * w + 9
    traced = Traced(
        np.array([surface, miss]),
        np.array([[5.5, 5.5], [9.5, 6.5]], np.float32),
        np.zeros(2),
        np.full(2, quincunx_offset(0.0)),
        np.array([2.0, np.inf], np.float32),
        np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]], np.float32),
    )
    alpha_min = 0.2
    blend = Blend(alpha_min, 0.05)
    _taa(traced, Tangents.of(cam), relative_view(cam, cam), blend, previous, True, Reprojected.empty())
    blended = alpha_min * np.array([0.0, 0.0, 1.0]) + (1 - alpha_min) * np.array([1.0, 0.0, 0.0])
    seen = [previous_depth == 2.0, previous_depth == FAR]  # the surface sample's taps, the miss's
    for k, hit in enumerate(seen):
        np.testing.assert_allclose(traced.rgb[k], blended if hit else (0.0, 0.0, 1.0), rtol=1e-6)
    np.testing.assert_array_equal(traced.depth, [2.0, FAR])  # the miss's capped, as level 0 is to hold it


def test_weier18_tangent_tables_are_the_rays_through_every_pixel_centre_bit_for_bit():
    """TAA looks up each sample's ray tangents by its pixel's column and row (weier18.Tangents): the same numbers
    pixel_tangents gives at that pixel's centre, on an off-centre frustum, so its back-projections are unchanged."""
    from hmdrt.foveation.weier18 import Tangents
    from hmdrt.optics.projection import camera_arrays, pixel_tangents

    cam = camera("dk2", width=37, height=23)
    tables = Tangents.of(cam)
    frustum = camera_arrays(cam).frustum
    assert frustum[0] != -frustum[1]  # an asymmetric frustum, as HMD eyes have
    for y in range(cam.height):
        for x in range(cam.width):
            tx, ty = pixel_tangents(frustum, x + 0.5, y + 0.5)
            assert (tables.x[x], tables.y[y]) == (tx, ty)
