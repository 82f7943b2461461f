"""Numerical stability at the edges: geometry through the real Embree tracer and the Whitted integrator."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from hmdrt.api import trace_gbuffer
from hmdrt.errors import SceneError
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import Scene, load_scene
from hmdrt.scene.model import Material, Mesh, PointLight
from hmdrt.scene.pack import pack
from hmdrt.scene.shapes import box, quad, sphere
from hmdrt.spatial import Pose as HeadPose
from hmdrt.trace.bsdf import fresnel_dielectric, refract, split
from hmdrt.trace.tracer import Tracer
from tests.stability.common import (
    SKY,
    camera,
)


def lambert(cam: EyeCamera, xy: np.ndarray, depth: np.ndarray, light: np.ndarray, intensity: float, normal, albedo):
    """Closed-form radiance of hits (depth along each pixel's ray): intensity cos / r^2 x albedo."""
    points = cam.position + depth[:, None].astype(np.float64) * cam.directions(xy).astype(np.float64)
    to_light = light - points
    r2 = np.einsum("ij,ij->i", to_light, to_light)
    cos = np.clip(to_light @ np.asarray(normal, float) / np.sqrt(r2), 0.0, None)
    return intensity * cos / r2 * np.asarray(albedo, float)[None, :].T


def test_sliver_and_degenerate_triangles_give_unit_normals_or_no_hit():
    """Slivers 2 m long and 2e-3 .. 2e-7 m wide, a line and a point triangle, in front of a backdrop."""
    slivers = []
    for i, aspect in enumerate((1e3, 1e5, 1e7)):
        y0, h = -0.6 + 0.6 * i, 2.0 / aspect
        v = np.array([[-1.0, y0, -2.0], [1.0, y0, -2.0], [1.0, y0 + h, -2.0]])
        slivers.append(Mesh(f"sliver{i}", v, np.array([[0, 1, 2]]), "m"))
    v = np.array([[0, 0, -2], [1, 0, -2], [2, 0, -2], [0, 1, -2], [0, 1, -2], [0, 1, -2]], float)
    degenerate = Mesh("deg", v, np.array([[0, 1, 2], [3, 4, 5]]), "m")
    backdrop = quad("back", (-5, -5, -3), (10, 0, 0), (0, 10, 0), "m")
    light = [PointLight(position=(0, 0, 1), intensity=(5, 5, 5))]
    scene = Scene("slivers", [*slivers, degenerate, backdrop], {"m": Material(specular=0.5)}, light)
    cam = camera(64, 64, centred=True)
    # every pixel centre, plus rays at each sliver's centroid (a third of its width from its edges)
    centroids = np.array([m.vertices.mean(axis=0) for m in slivers])
    xy = np.concatenate([pixel_centres(64, 64), cam.project(centroids)[0].astype(np.float32)])
    rgb, gbuf, _ = trace_gbuffer(scene, cam, xy)
    obj = gbuf.primary.object_id
    assert np.all(np.isfinite(rgb)) and np.all(obj >= 0)
    normals = gbuf.primary.normal_geometric
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(gbuf.primary.normal_shading, axis=1), 1.0, atol=1e-6)
    on_point = obj == 3  # a zero-area triangle, if Embree reports it at all, faces the ray
    np.testing.assert_allclose(normals[on_point], -cam.directions(xy)[on_point], atol=1e-6)
    # the two wider slivers are hit at their centroid, with the face normal +Z; the thinnest may be missed
    assert obj[-3] == 0 and obj[-2] == 1 and obj[-1] in (2, 4)
    np.testing.assert_allclose(normals[-3:-1], [[0, 0, 1], [0, 0, 1]], atol=1e-6)
    np.testing.assert_allclose(
        gbuf.primary.depth[-3:-1], np.linalg.norm(centroids[:2] - cam.position, axis=1), rtol=1e-6
    )


def test_coplanar_overlapping_triangles_shade_as_one_or_the_other_and_cast_no_shadow_on_each_other():
    red = quad("red", (-4, 0, 2), (8, 0, 0), (0, 0, -8), "red")
    blue = quad("blue", (-4, 0, 2), (8, 0, 0), (0, 0, -8), "blue")  # the same plane, the same triangles
    mats = {"red": Material(diffuse=(0.9, 0.1, 0.1)), "blue": Material(diffuse=(0.1, 0.1, 0.9))}
    light, intensity = np.array([0.5, 2.0, -1.0]), 4.0
    scene = Scene("coplanar", [red, blue], mats, [PointLight(position=tuple(light), intensity=(intensity,) * 3)])
    cam = camera(32, 32, HeadPose.looking((0.0, 1.0, 0.5), 0.0, -50.0))
    xy = pixel_centres(32, 32)
    rgb, gbuf, _ = trace_gbuffer(scene, cam, xy)
    again, gbuf2, _ = trace_gbuffer(scene, cam, xy)
    hit = gbuf.primary.object_id >= 0
    assert hit.sum() > 500 and set(np.unique(gbuf.primary.object_id[hit])) <= {0, 1}
    np.testing.assert_array_equal(rgb, again)  # the same choice every time
    np.testing.assert_array_equal(gbuf.primary.object_id, gbuf2.primary.object_id)
    assert np.all(gbuf.primary.shadow_count[hit] == 0)  # the coincident twin does not shadow the surface
    albedo = np.where((gbuf.primary.object_id[hit] == 0)[:, None], (0.9, 0.1, 0.1), (0.1, 0.1, 0.9))
    expected = lambert(cam, xy[hit], gbuf.primary.depth[hit], light, intensity, (0, 1, 0), (1, 1, 1)).T * albedo
    np.testing.assert_allclose(rgb[hit], expected, rtol=1e-4)


def test_rays_parallel_to_a_face_miss_it_or_hit_finitely():
    face = quad("q", (-1, 0, -1), (2, 0, 0), (0, 0, -2), "m")
    with Tracer(pack(Scene("t", [face], {"m": Material()})).geometry) as tracer:
        n = 200
        origins = np.zeros((n, 3), np.float32)
        origins[:, 0] = np.linspace(-1.5, 1.5, n)
        directions = np.tile(np.array([[0.0, 0.0, -1.0]], np.float32), (n, 1))  # in the face's plane
        for offset in (0.0, 1e-7, -1e-7):
            hits = tracer.intersect(origins + np.float32([0, offset, 0]), directions)
            assert np.all(np.isfinite(hits.t[hits.prim >= 0])) and np.all(np.isinf(hits.t[hits.prim < 0]))
            assert np.all(hits.t[hits.prim >= 0] <= 3.0 + 1e-5)
    cam = camera(32, 32, HeadPose.looking((0.0, 0.0, 1.0)))  # eye level with the face: the middle row grazes it
    rgb, gbuf, _ = trace_gbuffer(
        Scene("t", [face], {"m": Material()}, [PointLight(position=(0, 1, 0), intensity=(1, 1, 1))]),
        cam,
        pixel_centres(32, 32),
    )
    assert np.all(np.isfinite(rgb)) and np.all(np.isfinite(gbuf.primary.normal_shading))


@pytest.mark.parametrize("height", [1e-6, 1e6])
def test_hits_at_1e_minus_6_and_1e6_m_have_accurate_distances_and_closed_form_shading(height):
    """A camera `height` above a plane four times as wide, looking straight down, the light at twice the height."""
    half = 2.0 * height  # the view's footprint is +-1.07 height
    plane = quad("plane", (-half, 0, half), (2 * half, 0, 0), (0, 0, -2 * half), "m")
    light, intensity = np.array([0.3 * height, 2.0 * height, 0.0]), 3.0 * height * height
    scene = Scene(
        "plane",
        [plane],
        {"m": Material(diffuse=(0.5, 0.6, 0.7))},
        [PointLight(position=tuple(light), intensity=(intensity,) * 3)],
    )
    cam = camera(16, 16, HeadPose.looking((0.0, height, 0.0), 0.0, -90.0), centred=True)
    xy = pixel_centres(16, 16)
    rgb, gbuf, stats = trace_gbuffer(scene, cam, xy)
    dirs = cam.directions(xy).astype(np.float64)
    assert np.all(gbuf.primary.object_id == 0)
    np.testing.assert_allclose(gbuf.primary.depth, cam.position[1] / -dirs[:, 1], rtol=2e-6)
    assert np.all(gbuf.primary.shadow_count == 0) and stats.rays["shadow"] == 256  # no acne at either scale
    expected = lambert(cam, xy, gbuf.primary.depth, light, intensity, (0, 1, 0), (0.5, 0.6, 0.7)).T
    np.testing.assert_allclose(rgb, expected, rtol=1e-4)


def test_camera_inside_a_closed_mesh_sees_the_inside_lit_only_by_what_is_inside():
    mats = {"wall": Material(diffuse=(0.6, 0.5, 0.4))}
    room = box("room", (-1, -1, -1), (1, 1, 1), "wall")
    ambient = (0.2, 0.2, 0.2)
    outside = Scene("in", [room], mats, [PointLight(position=(0, 5, 0), intensity=(9, 9, 9))], ambient=ambient)
    cam = camera(16, 16, HeadPose.looking((0.1, 0.2, 0.3), 30.0, 10.0))
    xy = pixel_centres(16, 16)
    rgb, gbuf, _ = trace_gbuffer(outside, cam, xy)
    assert np.all(gbuf.primary.object_id == 0)  # every ray hits a wall from inside
    points = cam.position + gbuf.primary.depth[:, None] * cam.directions(xy).astype(np.float64)
    facing = np.einsum("ij,ij->i", np.array([0, 5, 0]) - points, gbuf.primary.normal_geometric) > 0
    assert facing.any() and np.all(gbuf.primary.shadow_count[facing] == 1)  # blocked wherever it could shine
    np.testing.assert_allclose(rgb, np.tile(np.multiply(ambient, (0.6, 0.5, 0.4)), (256, 1)), rtol=1e-6)
    light = np.array([0.0, 0.5, 0.0])
    inside = Scene("in", [room], mats, [PointLight(position=tuple(light), intensity=(2, 2, 2))])
    rgb, gbuf, _ = trace_gbuffer(inside, cam, xy)
    normals = gbuf.primary.normal_geometric.astype(np.float64)
    points = cam.position + gbuf.primary.depth[:, None] * cam.directions(xy).astype(np.float64)
    to_light = light - points
    r2 = np.einsum("ij,ij->i", to_light, to_light)
    cos = np.clip(np.einsum("ij,ij->i", to_light, normals) / np.sqrt(r2), 0, None)
    np.testing.assert_allclose(rgb, (2.0 * cos / r2)[:, None] * (0.6, 0.5, 0.4), rtol=1e-4, atol=1e-7)
    assert np.all(gbuf.primary.shadow_count == 0)


def glass_ball(max_depth: int) -> Scene:
    """A black, lossless glass sphere (all weight in Fresnel reflection and refraction) against a uniform sky."""
    mats = {"glass": Material(diffuse=(0.0, 0.0, 0.0), transmittance=1.0, ior=1.5)}
    ball = sphere("ball", (0.0, 0.0, -3.0), 1.0, "glass", subdivisions=5)
    return Scene("glass", [ball], mats, background=SKY, max_depth=max_depth)


def test_total_internal_reflection_at_grazing_angles_sends_everything_back():
    eta = 1.5  # glass to air
    critical = math.asin(1.0 / eta)
    for theta in (critical + 1e-9, 1.2, math.pi / 2 - 1e-9, math.pi / 2):
        cos_i = math.cos(theta)
        assert fresnel_dielectric(cos_i, eta) == 1.0
        assert split(0.0, 1.0, cos_i, eta) == (1.0, 0.0)  # all of it reflects
        ok, *_ = refract(math.sin(theta), 0.0, -cos_i, 0.0, 0.0, 1.0, eta)
        assert not ok
    for cos_i in (0.0, 1e-12):  # grazing from outside: total reflection in the limit, no NaN
        assert fresnel_dielectric(cos_i, 1.0 / eta) == pytest.approx(1.0, abs=1e-11)


def test_glass_sphere_at_grazing_angles_never_gains_energy():
    """Rays at impact parameters up to the silhouette, where the refracted ray meets the far side close to the
    critical angle (the tessellation's normals can tip it into total internal reflection); depth 16."""
    profile = msgspec.structs.replace(get_profile("sim-cpu").with_resolution(64, 64), ipd_mm=0.0)
    cam = EyeCamera.for_eye(profile, HeadPose())  # at the origin, the ball 3 m ahead
    ball = glass_ball(16)
    tri = ball.meshes[0].vertices[ball.meshes[0].faces] - (0.0, 0.0, -3.0)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inner = np.min(np.einsum("ij,ij->i", tri[:, 0], n / np.linalg.norm(n, axis=1, keepdims=True)))
    b = inner * np.concatenate([np.linspace(0.0, 0.99, 50), 1.0 - np.logspace(-2, -6, 50)])  # all inside the mesh
    tan = np.tan(np.arcsin(b / 3.0))
    xy = np.stack([(tan - cam.tan_left) / (cam.tan_right - cam.tan_left) * 64, np.full_like(b, 32.0)], axis=1)
    sky = np.array(SKY)
    rgb, gbuf, stats = trace_gbuffer(ball, cam, xy.astype(np.float32))
    assert np.all(gbuf.primary.object_id == 0) and stats.rays["secondary"] > 2 * len(b)
    assert np.all(np.isfinite(rgb)) and np.all(rgb <= sky * (1 + 1e-5))  # weights of a hit's children sum to 1
    np.testing.assert_allclose(rgb[:25], np.tile(sky, (25, 1)), rtol=1e-3)  # near normal incidence: all comes out
    assert np.all(rgb[50:] > 0.5 * sky)  # grazing: most is reflected straight off, none is lost to NaN


def test_recursion_depth_0_shows_only_local_shading_and_16_lets_the_sky_through():
    cam = camera(32, 32)
    xy = pixel_centres(32, 32)
    sky = np.array(SKY)
    rgb0, gbuf0, stats0 = trace_gbuffer(glass_ball(0), cam, xy)
    on_ball = gbuf0.primary.object_id == 0
    assert on_ball.sum() > 50 and stats0.rays["secondary"] == 0
    np.testing.assert_array_equal(rgb0[on_ball], 0.0)  # black glass without bounces
    np.testing.assert_allclose(rgb0[~on_ball], np.tile(sky, ((~on_ball).sum(), 1)), rtol=1e-6)
    rgb16, _, stats16 = trace_gbuffer(glass_ball(16), cam, xy)
    assert stats16.rays["secondary"] > 0 and np.all(np.isfinite(rgb16))
    assert np.all(rgb16 <= sky * (1 + 1e-5))
    centre = np.linalg.norm(xy - 16.0, axis=1) < 4.0  # near-normal incidence: little stays trapped
    np.testing.assert_allclose(rgb16[centre], np.tile(sky, (centre.sum(), 1)), rtol=1e-3)
    with pytest.raises(SceneError, match="outside"):
        load_scene("whitted?max_depth=17")
