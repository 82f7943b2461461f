"""Whitted shading: Snell, total internal reflection, Fresnel, energy, textures, lights and the G-buffer."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hmdrt.api import trace_gbuffer
from hmdrt.kernels.rng import uniform
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import Scene, load_scene
from hmdrt.scene.model import AreaLight, Checker, Image, Material, Noise, PointLight
from hmdrt.scene.noise import _grad
from hmdrt.scene.pack import pack
from hmdrt.scene.shapes import quad, sphere
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.bsdf import fresnel_dielectric, reflect, refract, split
from hmdrt.trace.gbuffer import GBuffer, GBufferPool, HitAttributes
from hmdrt.trace.integrator import Whitted
from hmdrt.trace.sampling import cosine_hemisphere, sincos_turn, stratified, tangent_frame
from hmdrt.trace.textures import sample_texture

from .helpers import render

unit = st.floats(-1.0, 1.0)


def _unit(v):
    v = np.asarray(v, float)
    return v / np.linalg.norm(v)


@settings(max_examples=300, deadline=None)
@given(theta=st.floats(0.0, 89.9), eta=st.floats(0.2, 5.0), phi=st.floats(0, 2 * math.pi))
def test_refraction_obeys_snell_and_total_internal_reflection(theta, eta, phi):
    n = np.array([0.0, 0.0, 1.0])
    t = math.radians(theta)
    d = np.array([math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), -math.cos(t)])  # arriving against n
    ok, tx, ty, tz = refract(*d, *n, eta)
    sin_t = eta * math.sin(t)
    if sin_t > 1.0 + 1e-9:
        assert not ok
        assert fresnel_dielectric(math.cos(t), eta) == 1.0
    elif sin_t < 1.0 - 1e-9:
        assert ok
        out = np.array([tx, ty, tz])
        assert abs(np.linalg.norm(out) - 1.0) < 1e-9
        assert out @ n < 0  # goes through the surface
        sin_out = np.linalg.norm(np.cross(out, n))
        assert math.isclose(sin_out, sin_t, abs_tol=1e-9)  # n1 sin(i) = n2 sin(t)
        assert abs(np.cross(d, n) @ out) < 1e-9  # stays in the plane of incidence


def test_fresnel_at_normal_incidence_and_grazing():
    assert math.isclose(fresnel_dielectric(1.0, 1 / 1.5), ((1.5 - 1) / (1.5 + 1)) ** 2, rel_tol=1e-12)
    assert fresnel_dielectric(1e-9, 1 / 1.5) > 0.999
    assert fresnel_dielectric(1.0, 1.0) == 0.0


@settings(max_examples=300, deadline=None)
@given(r=st.floats(0, 1), t=st.floats(0, 1), cos=st.floats(0, 1), eta=st.floats(0.2, 5.0))
def test_energy_never_rises_through_a_bounce(r, t, cos, eta):
    t = min(t, 1.0 - r)
    kr, kt = split(r, t, cos, eta)
    assert 0.0 <= kr and 0.0 <= kt
    assert kr + kt <= r + t + 1e-12 <= 1.0 + 1e-12
    assert math.isclose(kr + kt, r + t, abs_tol=1e-12)  # what is not reflected is transmitted


@given(dx=unit, dy=unit, dz=unit, nx=unit, ny=unit, nz=unit)
def test_reflection_keeps_length_and_mirrors_the_normal_component(dx, dy, dz, nx, ny, nz):
    if np.linalg.norm([nx, ny, nz]) < 1e-3 or np.linalg.norm([dx, dy, dz]) < 1e-3:
        return
    d, n = _unit([dx, dy, dz]), _unit([nx, ny, nz])
    r = np.array(reflect(*d, *n))
    assert math.isclose(np.linalg.norm(r), 1.0, rel_tol=1e-9)
    assert math.isclose(r @ n, -(d @ n), abs_tol=1e-9)


def test_reflected_radiance_never_exceeds_what_the_mirror_sees_directly():
    """A perfect mirror sphere (reflectance 1) shows nothing brighter than the scene it reflects."""
    mats = {
        "floor": Material(diffuse=(1, 1, 1), texture=Checker(colors=((0.2, 0.2, 0.2), (0.9, 0.9, 0.9)))),
        "mirror": Material(diffuse=(0, 0, 0), reflectance=1.0),
    }
    scene = Scene(
        "m",
        [
            quad("floor", (-20, 0, 20), (40, 0, 0), (0, 0, -40), "floor", (40, 40)),
            sphere("ball", (0, 1, -3), 1.0, "mirror"),
        ],
        mats,
        [PointLight(position=(0, 8, 0), intensity=(60, 60, 60))],
        background=(0.4, 0.6, 0.9),
        start=Pose.looking((0, 1.2, 1.0), 0, -10),
    )
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(64, 64), scene.start)
    rgb, gbuf, _ = trace_gbuffer(scene, cam, pixel_centres(64, 64))
    on_ball = gbuf.primary.object_id == 1
    direct = ~on_ball & (gbuf.primary.object_id >= 0)
    assert on_ball.sum() > 100
    brightest_direct = max(rgb[direct].max(), 0.9)  # floor seen directly, or the sky
    assert rgb[on_ball].max() <= brightest_direct + 1e-5
    np.testing.assert_allclose(gbuf.primary.reflect[on_ball], 1.0)


def test_glass_sphere_spawns_reflection_and_refraction(whitted_scene):
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(80, 90), whitted_scene.start)
    _, gbuf, stats = trace_gbuffer(whitted_scene, cam, pixel_centres(80, 90))
    glass = gbuf.primary.object_id == 2
    assert glass.sum() > 50
    kr, kt = gbuf.primary.reflect[glass], gbuf.primary.refract[glass]
    np.testing.assert_allclose(kr + kt, 0.95, atol=1e-6)  # transmittance 0.95, split by Fresnel
    f0 = ((1.5 - 1) / (1.5 + 1)) ** 2  # Fresnel reflectance at normal incidence, its minimum
    assert kr.min() >= 0.95 * f0 - 1e-6 and kt.max() <= 0.95 * (1 - f0) + 1e-6
    assert kt.max() > 0.9 * 0.95 * (1 - f0) and kr.max() > 3 * kr.min()  # near-normal centre, grazing rim
    # the heavier secondary ray of a glass pixel is the refracted one, which hits the glass again from inside
    assert np.mean(gbuf.secondary.object_id[glass] == 2) > 0.9
    assert stats.rays["secondary"] > 2 * glass.sum()


def test_checkerboard_is_exact_at_cell_centres():
    colors = ((0.9, 0.1, 0.2), (0.05, 0.6, 0.3))
    scale = 3.0
    mats = pack(
        Scene("c", [], {"c": Material(diffuse=(1, 1, 1), texture=Checker(colors=colors, scale=scale))})
    ).materials
    i, j = np.meshgrid(np.arange(-4, 5), np.arange(-4, 5))
    coords = np.stack([(i.ravel() + 0.5) / scale, (j.ravel() + 0.5) / scale, np.zeros(i.size)], axis=1)
    got = sample_texture(mats, 0, coords)
    parity = (i.ravel() + j.ravel()) & 1
    expected = np.array(colors, np.float32)[parity]
    np.testing.assert_array_equal(got, expected)


def test_noise_texture_stays_between_its_colours_and_varies():
    colors = ((0.1, 0.2, 0.3), (0.8, 0.7, 0.6))
    mats = pack(
        Scene("n", [], {"n": Material(diffuse=(1, 1, 1), texture=Noise(colors=colors, scale=5.0, seed=3))})
    ).materials
    rng = np.random.default_rng(0)
    got = sample_texture(mats, 0, rng.uniform(-10, 10, size=(2000, 3)))
    lo, hi = np.minimum(*colors), np.maximum(*colors)
    assert np.all(got >= lo - 1e-6) and np.all(got <= hi + 1e-6)
    assert got[:, 0].std() > 0.03


def test_image_texture_is_bilinear_and_wraps():
    img = np.zeros((2, 2, 3), np.float32)
    img[0, 0] = img[1, 1] = 1.0  # top-left and bottom-right white
    scene = Scene("i", [], {"i": Material(diffuse=(1, 1, 1), texture=Image(image="img"))}, images={"img": img})
    mats = pack(scene).materials
    # UV (0.25, 0.75) is the centre of the top-left texel; (0.5, 0.5) is the average of all four;
    # (1.25, -0.25) wraps around to the top-left texel; (0.0, 0.75) blends across the left-right seam
    uv = np.array([[0.25, 0.75, 0], [0.75, 0.75, 0], [0.5, 0.5, 0], [1.25, -0.25, 0], [0.0, 0.75, 0]])
    got = sample_texture(mats, 0, uv)
    np.testing.assert_allclose(got[:, 0], [1.0, 0.0, 0.5, 1.0, 0.5], atol=1e-6)


def test_point_light_shadow_is_counted_and_dark():
    mats = {"floor": Material(diffuse=(0.8, 0.8, 0.8)), "ball": Material(diffuse=(0.8, 0.2, 0.2))}
    scene = Scene(
        "s",
        [quad("floor", (-5, 0, 5), (10, 0, 0), (0, 0, -10), "floor"), sphere("ball", (0, 1.0, -3), 0.5, "ball")],
        mats,
        [PointLight(position=(0, 6, -3), intensity=(30, 30, 30))],
        start=Pose.looking((0, 3, 0), 0, -40),
    )
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(64, 64), scene.start)
    rgb, gbuf, _ = trace_gbuffer(scene, cam, pixel_centres(64, 64))
    floor = gbuf.primary.object_id == 0
    shadowed = floor & (gbuf.primary.shadow_count == 1)
    lit = floor & (gbuf.primary.shadow_count == 0)
    assert shadowed.sum() > 20 and lit.sum() > 200
    assert rgb[shadowed].max() < 1e-6  # no ambient: a hard shadow is black
    assert rgb[lit].min() > 0.01


def test_area_light_gives_a_soft_shadow_and_ao_darkens_corners():
    image, stats = render("interior", 64, 72)
    assert stats.rays["area"] > 0 and stats.rays["ao"] > 0 and stats.rays["shadow"] == 0
    scene = load_scene("interior")
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(64, 72), scene.start)
    _, gbuf, _ = trace_gbuffer(scene, cam, pixel_centres(64, 72))
    counts = gbuf.primary.shadow_count[gbuf.primary.object_id == 0]  # the floor
    samples = scene.lights[0].samples
    assert np.any((counts > 0) & (counts < samples))  # penumbra: partly shadowed points
    no_ao, _ = render("interior?ao_samples=0", 64, 72)
    assert image.mean() < no_ao.mean()  # occlusion only removes ambient light


def test_gbuffer_primary_depth_and_ids_match_the_tracer(whitted_scene):
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(48, 54), whitted_scene.start)
    xy = pixel_centres(48, 54)
    _, gbuf, _ = trace_gbuffer(whitted_scene, cam, xy)
    p = gbuf.primary
    sky = p.object_id < 0
    assert sky.any() and (~sky).any()
    assert np.all(np.isinf(p.depth[sky])) and np.all(np.isfinite(p.depth[~sky]))
    np.testing.assert_allclose(np.linalg.norm(p.normal_geometric[~sky], axis=1), 1.0, atol=1e-5)
    dirs = cam.directions(xy)
    assert np.all(np.einsum("ij,ij->i", p.normal_geometric[~sky], dirs[~sky]) <= 1e-6)  # faces the viewer
    floor = p.object_id == 0
    assert np.all(p.textured[floor]) and not np.any(p.textured[p.object_id == 1])
    hit_points = cam.position + dirs[floor] * p.depth[floor, None]
    np.testing.assert_allclose(hit_points[:, 1], 0.0, atol=1e-4)  # the floor is the plane y = 0


def test_a_gbuffer_keeps_the_attributes_asked_for_with_the_same_values_and_colours(whitted_scene):
    """A method keeps the attributes it reads (weier18 the primary hits' depth, kim21 Table 1's): the tracer stores
    those alone, with the values and colours of a full G-buffer's trace, bit for bit; the others hold no samples."""
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(48, 54), whitted_scene.start)
    xy = pixel_centres(48, 54)
    keys = np.arange(len(xy), dtype=np.int64)
    kept = {"primary": {"depth", "normal_geometric"}, "secondary": {"object_id"}}
    with Whitted(whitted_scene, 2) as tracer:
        traced = []
        for pool in (GBufferPool(), GBufferPool(("normal_geometric",), ("object_id",))):
            gbuf, rgb = pool.rows(len(xy))
            tracer.trace_samples(cam, xy, keys, FrameStats(), gbuf, out=rgb)
            traced.append((gbuf, rgb.copy()))
    (full, full_rgb), (some, rgb) = traced
    np.testing.assert_array_equal(rgb, full_rgb)
    assert (full.secondary.object_id >= 0).any()  # the mirror and glass spheres' reflections were stored there
    for half in ("primary", "secondary"):
        for name in HitAttributes._fields:
            ours, theirs = getattr(getattr(some, half), name), getattr(getattr(full, half), name)
            if name in kept[half]:
                np.testing.assert_array_equal(ours, theirs)
            else:
                assert len(ours) == 0, (half, name)
    with pytest.raises(ValueError, match="no G-buffer attribute"):
        GBufferPool(("normals",))


def test_a_gbuffer_stores_the_kept_samples_attributes_and_every_depth(whitted_scene):
    """GBuffer.kept (kim21 reads Table 1 in its central region only): the tracer stores the attributes of the kept
    samples, as a full trace does, and every sample's primary depth; the other samples' attributes stay as they
    were (the secondary half's misses, as a caller clears them); a mask shorter than the samples is refused."""
    cam = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(48, 54), whitted_scene.start)
    xy = pixel_centres(48, 54)
    keys = np.arange(len(xy), dtype=np.int64)
    kept = (np.arange(len(xy)) % 3 == 0) | (np.arange(len(xy)) > 2000)
    with Whitted(whitted_scene, 2) as tracer:
        full = GBuffer.empty(len(xy))
        tracer.trace_samples(cam, xy, keys, FrameStats(), full)
        masked = GBuffer.empty(len(xy))._replace(kept=kept)
        masked.primary.object_id.fill(-7)
        masked.primary.normal_shading.fill(5.0)
        tracer.trace_samples(cam, xy, keys, FrameStats(), masked)
        with pytest.raises(ValueError, match="kept holds 10 samples"):
            tracer.trace_samples(cam, xy, keys, FrameStats(), masked._replace(kept=kept[:10]))
    np.testing.assert_array_equal(masked.primary.depth, full.primary.depth)
    for half in ("primary", "secondary"):
        ours, theirs = getattr(masked, half), getattr(full, half)
        for name in ("object_id", "normal_shading", "shadow_count", "textured"):
            np.testing.assert_array_equal(getattr(ours, name)[kept], getattr(theirs, name)[kept], err_msg=name)
    assert np.all(masked.primary.object_id[~kept] == -7) and np.all(masked.primary.normal_shading[~kept] == 5.0)
    assert (full.secondary.object_id[~kept] >= 0).any() and np.all(masked.secondary.object_id[~kept] == -1)


def test_stages_a_scene_cannot_use_are_not_run():
    _, whitted = render("whitted", 32, 32)
    _, tunnel = render("tunnel_maps", 32, 32)
    assert "secondary" in whitted.stages_ms and whitted.rays["secondary"] > 0
    assert "secondary" not in tunnel.stages_ms and tunnel.rays["secondary"] == 0
    for stats in (whitted, tunnel):
        assert "area" not in stats.stages_ms and "ao" not in stats.stages_ms
        assert stats.rays["area"] == stats.rays["ao"] == 0
    _, flat = render("whitted?max_depth=0", 32, 32)
    assert "secondary" not in flat.stages_ms


def test_renders_are_reproducible_and_seeded():
    a, _ = render("interior", 32, 36, seed=7)
    b, _ = render("interior", 32, 36, seed=7)
    c, _ = render("interior", 32, 36, seed=8)
    np.testing.assert_array_equal(a, b)
    assert np.abs(a - c).max() > 0


def test_result_does_not_depend_on_batching(monkeypatch):
    import hmdrt.trace.integrator as integrator

    a, _ = render("interior", 40, 40)
    monkeypatch.setattr(integrator, "RAYS_PER_CHUNK", 5000)
    b, _ = render("interior", 40, 40)
    np.testing.assert_array_equal(a, b)


def test_area_light_must_have_area():
    import msgspec

    with pytest.raises(msgspec.ValidationError, match="non-zero area"):
        msgspec.convert(
            {"kind": "area", "corner": [0, 0, 0], "edge_u": [1, 0, 0], "edge_v": [2, 0, 0], "radiance": [1, 1, 1]},
            AreaLight,
        )


# -- the light rays' sampling: fast sine and cosine, the cosine-weighted hemisphere, Perlin's gradients --


def test_sincos_turn_matches_libm_across_every_quadrant():
    t = np.concatenate([np.linspace(0.0, 1.0, 4097), np.random.default_rng(1).random(20_000)])
    got = np.array([sincos_turn(v) for v in t])
    np.testing.assert_allclose(got[:, 0], np.sin(2 * np.pi * t), rtol=0, atol=2e-15)
    np.testing.assert_allclose(got[:, 1], np.cos(2 * np.pi * t), rtol=0, atol=2e-15)


@pytest.mark.parametrize("normal", [(0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (0.6, -0.48, -0.64), (1.0, 0.0, 0.0)])
def test_ao_directions_are_cosine_weighted_about_the_normal(normal):
    """Unit directions in the normal's hemisphere whose cosine to it has the cosine-weighted mean 2/3 and
    second moment 1/2, and no azimuth preferred."""
    n = np.array(normal)
    frame = tangent_frame(*n)
    np.testing.assert_allclose(np.array([n, *frame]) @ np.array([n, *frame]).T, np.eye(3), atol=1e-12)
    st_ = np.random.default_rng(2).random((40_000, 2))
    d = np.array([cosine_hemisphere(tuple(n), *frame, s, t) for s, t in st_])
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    cos = d @ n
    assert cos.min() >= 0.0
    assert abs(cos.mean() - 2 / 3) < 0.01 and abs((cos**2).mean() - 0.5) < 0.01
    assert np.linalg.norm((d - np.outer(cos, n)).mean(axis=0)) < 0.01


@pytest.mark.parametrize("nx, ny", [(1, 1), (2, 4), (3, 3), (7, 9), (64, 64), (1, 4096)])
def test_stratified_takes_the_kth_stratum_row_by_row(nx, ny):
    """Sample k lies in stratum (k mod nx, k div nx), found without integer division, and is that stratum's
    corner plus the key's two uniforms over its size, exactly."""
    key, dim = 123456789012, 16
    for k in range(nx * ny):
        s, t = stratified(key, k, dim, nx, ny)
        assert (s, t) == ((k % nx + uniform(key, dim, 2 * k)) / nx, (k // nx + uniform(key, dim, 2 * k + 1)) / ny)
    for k in (2**31 - 1, 2**40 - 3):  # far past any sample count: the row still exact
        s, t = stratified(key, k, dim, nx, ny)
        assert t == (k // nx + uniform(key, dim, 2 * k + 1)) / ny


def test_noise_gradients_are_perlins_twelve_edges():
    """Improved Perlin noise's gradients (Perlin 2002, in his reference code's order): h & 15 picks one of the
    cube's 12 edge directions, four of them twice."""
    edges = [(1, 1, 0), (-1, 1, 0), (1, -1, 0), (-1, -1, 0), (1, 0, 1), (-1, 0, 1), (1, 0, -1), (-1, 0, -1)]
    edges += [(0, 1, 1), (0, -1, 1), (0, 1, -1), (0, -1, -1), (1, 1, 0), (0, -1, 1), (-1, 1, 0), (0, -1, -1)]
    x, y, z = 0.3, -0.7, 1.9
    for h in range(64):
        gx, gy, gz = edges[h & 15]
        assert _grad(h, x, y, z) == pytest.approx(gx * x + gy * y + gz * z, abs=1e-15), h
