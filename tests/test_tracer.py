"""The Embree tracer: hit distances, differential agreement with trimesh, robustness and self-intersection."""

import threading

import numpy as np
import pytest

from hmdrt.api import trace_gbuffer
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import Scene, load_scene
from hmdrt.scene.builtin import bunny
from hmdrt.scene.model import Material, Mesh, PointLight
from hmdrt.scene.pack import pack
from hmdrt.scene.shapes import quad, sphere
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.blocks import BLOCK
from hmdrt.trace.embree import PACKET
from hmdrt.trace.gbuffer import GBuffer, HitAttributes, LightBuffer
from hmdrt.trace.integrator import Whitted
from hmdrt.trace.tracer import Tracer
from hmdrt.trace.wavefront import TILE_COLUMNS, TILE_ROWS, _band_start, _tile_order

from .helpers import render


def _tracer(meshes) -> Tracer:
    mats = {"m": Material()}
    return Tracer(pack(Scene("t", meshes, mats)).geometry)


def test_sphere_hit_distance_matches_the_analytic_value():
    centre, radius = np.array([0.3, -0.2, -5.0]), 1.25
    mesh = sphere("s", centre, radius, "m", subdivisions=6)
    # the tessellation lies between the circumscribed sphere and the sphere through its face planes
    tri = mesh.vertices[mesh.faces]
    normals = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    inner = np.min(np.einsum("ij,ij->i", tri[:, 0] - centre, normals))
    rng = np.random.default_rng(3)
    offsets = rng.normal(size=(500, 3))
    offsets *= 0.8 * radius * rng.random((500, 1)) ** (1 / 3) / np.linalg.norm(offsets, axis=1, keepdims=True)
    target = centre + offsets  # inside the sphere, so every ray hits
    dirs = (target / np.linalg.norm(target, axis=1, keepdims=True)).astype(np.float32)
    origins = np.zeros_like(dirs)
    with _tracer([mesh]) as tr:
        hits = tr.intersect(origins, dirs)

    def analytic(r):
        b = dirs @ centre
        return b - np.sqrt(b * b - (centre @ centre - r * r))

    assert np.all(hits.prim >= 0)
    assert np.all(hits.t >= analytic(radius) - 1e-5)
    assert np.all(hits.t <= analytic(inner) + 1e-5)
    assert np.max(np.abs(hits.t - analytic(radius))) < 2e-3


def _brute_force_first_hit(vertices, faces, origins, dirs):
    """Moller-Trumbore against every triangle in float64: the slow, independent oracle."""
    tri = vertices[faces]
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    first = np.full(len(origins), -1)
    for r, (o, d) in enumerate(zip(origins.astype(np.float64), dirs.astype(np.float64), strict=True)):
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-12
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = o - v0
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ d) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        valid = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-9)
        if valid.any():
            first[r] = np.flatnonzero(valid)[np.argmin(t[valid])]
    return first


def test_embree_agrees_with_a_brute_force_intersector():
    mesh = bunny().meshes[0]
    mesh.material = "m"
    cam = EyeCamera.for_eye(
        get_profile("sim-cpu").with_resolution(40, 40), Pose.look_at((0, 0.45, -2.0), (0, 0.45, -2.6))
    )
    dirs = cam.directions(pixel_centres(40, 40))
    origins = np.tile(cam.position.astype(np.float32), (len(dirs), 1))
    with _tracer([mesh]) as tr:
        ours = tr.intersect(origins, dirs)
    theirs = _brute_force_first_hit(mesh.vertices, mesh.faces, origins, dirs)
    hit = theirs >= 0
    assert 0.2 < hit.mean() < 0.9  # the view sees both bunny and background
    assert np.mean((ours.prim >= 0) == hit) > 0.995
    both = hit & (ours.prim >= 0)
    assert np.mean(ours.prim[both] == theirs[both]) > 0.99


def test_degenerate_triangles_and_grazing_rays_give_no_nan():
    v = np.array([[0, 0, -2], [1, 0, -2], [2, 0, -2], [0, 1, -2], [0, 1, -2], [0, 1, -2]], float)
    degenerate = Mesh("deg", v, np.array([[0, 1, 2], [3, 4, 5]]), "m")  # a line and a point
    floor = quad("floor", (-5, -1, 5), (10, 0, 0), (0, 0, -10), "m")
    mats = {"m": Material(specular=0.5, reflectance=0.3, transmittance=0.3)}
    scene = Scene("deg", [degenerate, floor], mats, [PointLight(position=(0, 3, 0), intensity=(5, 5, 5))])
    cam = EyeCamera.for_eye(
        get_profile("sim-cpu").with_resolution(32, 32), Pose.looking((0, -1.0, 0))
    )  # eye level with the floor
    xy = pixel_centres(32, 32)
    rgb, gbuf, _ = trace_gbuffer(scene, cam, xy)
    assert np.all(np.isfinite(rgb))
    assert np.all(np.isfinite(gbuf.primary.normal_shading))


def test_empty_scene_traces_to_background():
    scene = Scene("empty", [], {"m": Material()}, background=(0.2, 0.3, 0.4))
    image, stats = render(scene, 8, 8)
    np.testing.assert_allclose(image.reshape(-1, 3), np.tile([0.2, 0.3, 0.4], (64, 1)), rtol=1e-6)
    assert stats.rays["shadow"] == 0


def _lit_plane(scale: float) -> Scene:
    """A plane under a point light, everything scaled by `scale`; no surface can shadow itself."""
    plane = quad("plane", (-10 * scale, 0, 10 * scale), (20 * scale, 0, 0), (0, 0, -20 * scale), "m")
    ball = sphere("ball", (0.0, 1.0 * scale, -4.0 * scale), 0.5 * scale, "mirror", subdivisions=4)
    mats = {"m": Material(diffuse=(0.7, 0.7, 0.7)), "mirror": Material(reflectance=0.9, diffuse=(0, 0, 0))}
    light = PointLight(position=(1.0 * scale, 5.0 * scale, 1.0 * scale), intensity=(25.0 * scale**2,) * 3)
    return Scene(
        "plane",
        [plane, ball],
        mats,
        [light],
        background=(0.3, 0.5, 0.8),
        start=Pose.looking((0.0, 1.5 * scale, 2.0 * scale), 0.0, -25.0),
    )


@pytest.mark.parametrize("scale", [1e-4, 1e4])
def test_self_intersection_offsets_hold_across_scales(scale):
    reference, _ = render(_lit_plane(1.0), 48, 48, ipd_mm=0.0)
    scaled, _ = render(_lit_plane(scale), 48, 48, ipd_mm=0.0)
    np.testing.assert_allclose(scaled, reference, atol=2e-3)


def test_a_lit_plane_has_no_shadow_acne():
    scene = _lit_plane(1.0)
    scene.meshes = scene.meshes[:1]  # the plane alone: nothing can shadow it
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(64, 64), scene.start)
    _, gbuf, stats = trace_gbuffer(scene, cam, pixel_centres(64, 64))
    on_plane = gbuf.primary.object_id == 0
    assert on_plane.sum() > 1000
    assert stats.rays["shadow"] == on_plane.sum()
    assert np.all(gbuf.primary.shadow_count[on_plane] == 0)


def test_intersect_validates_its_input():
    with _tracer([quad("q", (0, 0, 0), (1, 0, 0), (0, 1, 0), "m")]) as tr:
        with pytest.raises(TypeError):
            tr.intersect(np.zeros((2, 3)), np.zeros((2, 3)))
        with pytest.raises(ValueError):
            tr.intersect(np.zeros((2, 3), np.float32), np.zeros((3, 3), np.float32))
        assert len(tr.intersect(np.zeros((0, 3), np.float32), np.zeros((0, 3), np.float32)).prim) == 0


@pytest.mark.parametrize("threads", [1, 2])
def test_occluded_reports_rays_it_does_not_trace_as_unoccluded(threads):
    """tfar <= 0 (lighting's -1: the light is behind the surface) is not traced: False, though a wall blocks it."""
    wall = quad("wall", (-50, -50, -2), (100, 0, 0), (0, 100, 0), "m")  # across every ray, 2 m ahead
    n = 3 * BLOCK + 5  # several blocks, and a packet left partly empty
    rng = np.random.default_rng(11)
    far = rng.choice(np.float32([-1.0, 0.0, 1.0, 10.0]), n)  # untraced, untraced, short of the wall, through it
    origins = np.zeros((n, 3), np.float32)
    dirs = np.tile(np.float32([0.0, 0.0, -1.0]), (n, 1))
    with Tracer(pack(Scene("t", [wall], {"m": Material()})).geometry, threads=threads) as tr:
        blocked = tr.occluded(origins, dirs, far)
        np.testing.assert_array_equal(blocked, far == 10.0)
        assert not tr.occluded(origins, dirs, -1.0).any() and tr.occluded(origins, dirs, 10.0).all()


def test_direct_embree_agrees_with_embreex_and_with_itself_on_two_threads():
    """The numba-side Embree calls (hmdrt.trace.embree) give embreex's hits ray by ray, on any thread count."""
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    scene = bunny()
    geometry = pack(scene).geometry
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(96, 96), scene.start)
    dirs = cam.directions(pixel_centres(96, 96))
    origins = np.tile(cam.position.astype(np.float32), (len(dirs), 1))
    reference = rtcore_scene.EmbreeScene()
    TriangleMesh(reference, geometry.vertices, geometry.faces)
    want = reference.run(origins, dirs, output=1)
    with Tracer(geometry, threads=1) as one, Tracer(geometry, threads=2) as many:
        a, b = one.intersect(origins, dirs), many.intersect(origins, dirs)
        far = np.full(len(dirs), float(np.median(a.t[a.prim >= 0])), np.float32)
        blocked_one, blocked_many = one.occluded(origins, dirs, far), many.occluded(origins, dirs, far)
    hit = want["primID"] >= 0
    assert 0 < hit.sum() < len(dirs)
    np.testing.assert_array_equal(a.prim, want["primID"])
    np.testing.assert_allclose(a.t[hit], want["tfar"][hit], rtol=1e-6)
    np.testing.assert_allclose(a.u[hit], want["u"][hit], atol=1e-6)
    np.testing.assert_allclose(a.v[hit], want["v"][hit], atol=1e-6)
    np.testing.assert_array_equal(a.prim, b.prim)
    np.testing.assert_array_equal(a.t, b.t)
    np.testing.assert_array_equal(blocked_one, blocked_many)
    assert 0 < blocked_one.sum() < len(dirs)


def test_share_runs_each_share_once_the_first_on_the_caller_and_raises_a_failed_one():
    """Tracer.share: work(0) on the calling thread, work(1..threads-1) on the pool; an error comes back once all
    shares have ended."""
    with Tracer(pack(bunny()).geometry, threads=2) as tr:
        ran: list[tuple[int, int]] = []
        tr.share(lambda t: ran.append((t, threading.get_ident())))
        assert sorted(t for t, _ in ran) == list(range(tr.threads))
        assert dict(ran)[0] == threading.get_ident()
        ended = []

        def fail_last(t: int) -> None:
            if t == tr.threads - 1:
                raise ValueError("the last share failed")
            ended.append(t)

        with pytest.raises(ValueError, match="the last share failed"):
            tr.share(fail_last)
        assert sorted(ended) == list(range(tr.threads - 1))


def test_whitted_traces_the_same_on_one_thread_and_on_two():
    """The tracer's threads claim blocks as each frees up, each on its own scratch (lane): which thread traces a
    block changes no sample, nor the rays counted."""
    scene = load_scene("whitted")
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(64, 72), scene.start)
    xy = pixel_centres(64, 72)
    keys = np.arange(len(xy), dtype=np.int64)
    results = []
    for threads in (1, 2):
        stats = FrameStats()
        with Whitted(scene, threads=threads) as tracer:
            results.append((tracer.trace_samples(cam, xy, keys, stats), stats.rays))
    (one, rays_one), (two, rays_two) = results
    np.testing.assert_array_equal(one, two)
    assert rays_one == rays_two and rays_one["secondary"] > 0


def _scanline_subset(w: int, h: int, fraction: float, seed: int) -> np.ndarray:
    """Pixel centres of a random subset of a w x h image, in scanline order (as the foveated methods list them)."""
    xy = pixel_centres(w, h)
    return xy[np.random.default_rng(seed).random(len(xy)) < fraction]


@pytest.mark.parametrize("fraction", [1.0, 0.3])
def test_tile_order_merges_each_band_of_four_rows_by_pairs_of_columns(fraction):
    """Samples in scanline order are traced in bands of TILE_ROWS rows, by group of TILE_COLUMNS columns, then row: a
    packet of dense camera rays covers TILE_COLUMNS x 4 pixels; in any other order they are still each listed
    once."""
    xy = _scanline_subset(37, 23, fraction, 1)
    listed = np.full(len(xy), -1, np.int64)
    _tile_order(xy, len(xy), listed)
    rows, columns = xy[:, 1].astype(int), xy[:, 0].astype(int)
    expected = np.lexsort((columns, rows, columns // TILE_COLUMNS, rows // TILE_ROWS))
    np.testing.assert_array_equal(listed, expected)
    if fraction == 1.0:  # the first packet: the first TILE_COLUMNS pixels of each of the first four rows
        tile = (37 * np.arange(TILE_ROWS)[:, None] + np.arange(TILE_COLUMNS)).ravel()
        np.testing.assert_array_equal(listed[:PACKET], tile)
    shuffled = xy[np.random.default_rng(2).permutation(len(xy))]
    _tile_order(shuffled, len(xy), listed)
    np.testing.assert_array_equal(np.sort(listed), np.arange(len(xy)))


def test_block_bounds_move_back_to_the_start_of_their_band_within_reach():
    """A block's bounds move back to the first sample of their band of TILE_ROWS rows, so that _tile_order sees
    whole bands, but by no more than `reach` samples (a block then holds at most 1.5 blocks); the ends stay put."""
    xy = pixel_centres(10, 13)  # bands of 40 samples: rows 0-3, 4-7, 8-11, then row 12 alone
    n = len(xy)
    assert [_band_start(xy, s, 20) for s in (0, 45, 60, 61, 100, 125, n)] == [0, 40, 40, 61, 80, 120, n]
    assert _band_start(xy, 15, 20) == 0  # within reach of the first sample
    assert _band_start(xy, 79, 20) == 79  # its band began 39 samples before: out of reach
    bounds = np.array([_band_start(xy, min(n, b * 64), 32) for b in range(-(-n // 64) + 1)])  # blocks of 64
    sizes = np.diff(bounds)
    assert bounds[0] == 0 and bounds[-1] == n and sizes.min() > 0 and sizes.max() <= 64 + 32


@pytest.mark.parametrize("scene_name", ["whitted", "interior"])
def test_a_sample_traces_the_same_in_whatever_order_it_is_listed(scene_name):
    """The tracer traces a block's rays in tiles, not in the samples' order: each sample's radiance, G-buffer rows and
    light buffer are the same, bit for bit, wherever it stands in the list (its secondary rays, area and AO samples
    among them), and every sample's results land on its own rows."""
    scene = load_scene(scene_name)
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(96, 80), scene.start)
    xy = _scanline_subset(96, 80, 0.4, 3)
    keys = np.random.default_rng(4).integers(0, 2**40, len(xy))
    shuffle = np.random.default_rng(5).permutation(len(xy))
    traced = []
    with Whitted(scene, 2) as tracer:
        for order in (np.arange(len(xy)), shuffle):
            gbuf, light = GBuffer.empty(len(xy)), LightBuffer.empty(len(xy))
            rgb = tracer.trace_samples(cam, xy[order], keys[order], FrameStats(), gbuf, light)
            traced.append((order, rgb, gbuf, light))
    (_, rgb, gbuf, light), (order, rgb_s, gbuf_s, light_s) = traced
    np.testing.assert_array_equal(rgb_s, rgb[order])
    np.testing.assert_array_equal(light_s.irradiance, light.irradiance[order])
    np.testing.assert_array_equal(light_s.albedo, light.albedo[order])
    for half in ("primary", "secondary"):
        for name in HitAttributes._fields:
            ours, theirs = getattr(getattr(gbuf_s, half), name), getattr(getattr(gbuf, half), name)
            np.testing.assert_array_equal(ours, theirs[order], err_msg=f"{half}.{name}")
    assert (gbuf.secondary.object_id >= 0).any() or scene_name == "interior"
    assert np.ptp(rgb) > 0
