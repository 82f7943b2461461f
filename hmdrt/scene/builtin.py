"""Built-in procedural scenes that reproduce the papers' test content.

whitted: the classic Whitted scene of smith2013 section 6 (checkerboard floor, mirror and glass
spheres, one point light). tunnel_maps / tunnel_geom: the tunnels of weier2016 section 5 (a tunnel
textured with a high-contrast checkerboard and a noise texture; a tunnel of noisy displaced
geometry). voxel_city: Minecraft-like blocks with many depth discontinuities (the Rungholt role in
weier2016 and kim2021), `size` knob past 1M triangles. shooting_range: weier2018 section 5's long
tunnel with targets at 0.5-6 m, ~200K triangles. interior: a room with an area light for AO and
area-light sampling (kim2021's Interior role). bunny: smith2013's high-polygon Stanford bunny scene.
"""

from __future__ import annotations

import inspect
import math
from collections.abc import Callable
from importlib import resources

import numpy as np

from hmdrt.errors import SceneError
from hmdrt.ranges import MAX_SCENE_TRIANGLES, refuse_large
from hmdrt.scene import shapes
from hmdrt.scene.model import AreaLight, Checker, Light, Material, Mesh, Noise, PointLight, Scene
from hmdrt.scene.noise import fbm_points
from hmdrt.spatial import Pose

SKY = (0.35, 0.55, 0.85)
# smith2013's spheres: a mirror and a glass ball
MIRROR = Material(diffuse=(0.1, 0.1, 0.1), specular=0.6, shininess=80, reflectance=0.85)
GLASS = Material(diffuse=(0.0, 0.0, 0.0), specular=0.6, shininess=160, transmittance=0.95, ior=1.5)
MAPS_SEGMENTS, MAPS_RINGS = 96, 12  # per tunnel_maps section
GEOM_SEGMENTS, GEOM_RINGS_PER_M = 256, 10  # of tunnel_geom at detail 1
# voxel_city's plots hold 1-3 x 1-3 voxels of 1-16 high, 12 triangles each: 2 x 2 x 8.5 x 12 on average
PLOT_TRIANGLES = 408


def _under_sky(
    name: str,
    meshes: list[Mesh],
    mats: dict[str, Material],
    lights: list[Light],
    start: Pose,
    ambient: tuple[float, float, float] = (0.1, 0.1, 0.1),
) -> Scene:
    """An open scene: rays that leave it see the sky."""
    return Scene(name, meshes, mats, lights, background=SKY, ambient=ambient, start=start)


def whitted() -> Scene:
    """Checkerboard floor, a mirror sphere behind a glass sphere, one point light."""
    mats = {
        "floor": Material(diffuse=(1, 1, 1), texture=Checker(colors=((0.85, 0.1, 0.05), (0.95, 0.85, 0.1)))),
        "mirror": MIRROR,
        "glass": GLASS,
    }
    meshes = [
        shapes.quad("floor", (-20, 0, 8), (40, 0, 0), (0, 0, -60), "floor", uv_scale=(40, 60)),
        shapes.sphere("mirror_sphere", (0.55, 1.0, -4.2), 0.8, "mirror", subdivisions=5),
        shapes.sphere("glass_sphere", (-0.45, 0.8, -2.6), 0.55, "glass", subdivisions=5),
    ]
    lights = [PointLight(position=(-3.0, 7.0, 1.5), intensity=(60.0, 60.0, 60.0))]
    return _under_sky("whitted", meshes, mats, lights, Pose.looking((0.0, 1.25, 0.0), 0.0, -10.0))


def _tunnel_scene(name: str, meshes: list[Mesh], mats: dict[str, Material], length: float) -> Scene:
    """A tunnel along -Z lit by five point lights on its axis, seen from its mouth."""
    lights = [PointLight(position=(0.0, 0.6, -z), intensity=(2.5,) * 3) for z in np.linspace(4, length - 10, 5)]
    return Scene(name, meshes, mats, lights, ambient=(0.06, 0.06, 0.06), start=Pose.looking((0.0, -0.4, 0.0)))


def tunnel_maps(length: float = 60.0, section: float = 6.0) -> Scene:
    """A round tunnel whose sections alternate a black-and-white checkerboard and a noise texture."""
    mats = {
        "checker": Material(diffuse=(1, 1, 1), texture=Checker(scale=1.0)),
        "noise": Material(
            diffuse=(1, 1, 1), texture=Noise(colors=((0.1, 0.08, 0.05), (0.9, 0.85, 0.7)), scale=4.0, octaves=5)
        ),
    }
    radius = 2.0
    n_sections = max(1, int(round(length / section)))
    meshes = [
        shapes.tunnel(
            f"section_{i}",
            radius,
            section,
            "checker" if i % 2 == 0 else "noise",
            segments=MAPS_SEGMENTS,
            rings=MAPS_RINGS,
            z0=2.0 - i * section,
            uv_scale=(16, section),
        )
        for i in range(n_sections)
    ]
    return _tunnel_scene("tunnel_maps", meshes, mats, length)


def tunnel_geom(length: float = 60.0, detail: int = 1) -> Scene:
    """A round tunnel whose wall is displaced by fractal noise (~300K triangles at detail 1)."""
    mats = {"rock": Material(diffuse=(0.7, 0.66, 0.6), specular=0.15, shininess=24)}
    radius = 2.0

    def bumpy(theta, z):
        pts = np.stack([np.cos(theta) * 1.5, np.sin(theta) * 1.5, z * 0.75], axis=1)
        return radius + 0.45 * fbm_points(pts, octaves=5, seed=7)

    segments, rings = GEOM_SEGMENTS * detail, int(GEOM_RINGS_PER_M * length) * detail
    meshes = [shapes.tunnel("wall", radius, length, "rock", segments, rings, radius_fn=bumpy, z0=2.0)]
    return _tunnel_scene("tunnel_geom", meshes, mats, length)


def voxel_city(size: int = 24, seed: int = 1) -> Scene:
    """size x size city plots of unit-cube buildings; size=50 passes 1M triangles."""
    rng = np.random.default_rng(seed)
    palette = [(0.75, 0.72, 0.65), (0.55, 0.35, 0.25), (0.4, 0.45, 0.5), (0.8, 0.8, 0.8), (0.35, 0.5, 0.3)]
    mats = {f"block_{i}": Material(diffuse=c, specular=0.05) for i, c in enumerate(palette)}
    mats["street"] = Material(diffuse=(1, 1, 1), texture=Checker(colors=((0.25, 0.25, 0.25), (0.3, 0.3, 0.3))))
    plot = 4  # metres per plot: a building of up to 3x3 voxels and a 1 m street
    lo_by_mat: list[list[np.ndarray]] = [[] for _ in palette]
    for px in range(size):
        for pz in range(size):
            bx, bz = rng.integers(1, 4, size=2)
            h = int(rng.integers(1, 17))
            xs, ys, zs = np.mgrid[0:bx, 0:h, 0:bz]
            cubes = np.stack([xs.ravel() + px * plot, ys.ravel(), -(zs.ravel() + pz * plot) - 1], axis=1)
            lo_by_mat[int(rng.integers(len(palette)))].append(cubes)
    meshes = [
        shapes.boxes(f"blocks_{i}", np.concatenate(c).astype(np.float64), np.concatenate(c) + 1.0, f"block_{i}")
        for i, c in enumerate(lo_by_mat)
        if c
    ]
    extent = size * plot + 8
    meshes.append(
        shapes.quad("ground", (-8, 0, 8), (extent, 0, 0), (0, 0, -extent), "street", uv_scale=(extent, extent))
    )
    lights = [PointLight(position=(-120.0, 260.0, 90.0), intensity=(9.0e4, 8.6e4, 8.0e4))]
    start = Pose.look_at((-6.0, 18.0, 6.0), (size * plot * 0.45, 0.0, -size * plot * 0.45))
    return _under_sky("voxel_city", meshes, mats, lights, start, ambient=(0.18, 0.2, 0.24))


def shooting_range() -> Scene:
    """A long corridor with spheres and boxes at 0.5-6 m and a big blue ball at 6 m (~200K triangles)."""
    mats = {
        "wall": Material(diffuse=(0.55, 0.57, 0.6)),
        "floor": Material(diffuse=(1, 1, 1), texture=Checker(colors=((0.2, 0.2, 0.22), (0.6, 0.6, 0.62)))),
        "target": Material(diffuse=(0.85, 0.25, 0.1), specular=0.3, shininess=48),
        "crate": Material(diffuse=(0.6, 0.45, 0.25), specular=0.05),
        "blue": Material(diffuse=(0.1, 0.25, 0.85), specular=0.4, shininess=64),
    }
    w, h, length = 4.0, 3.0, 40.0
    meshes = [
        shapes.quad("floor", (-w / 2, 0, 1), (w, 0, 0), (0, 0, -length), "floor", uv_scale=(w * 2, length * 2)),
        shapes.quad("ceiling", (-w / 2, h, 1), (0, 0, -length), (w, 0, 0), "wall"),
        shapes.quad("left", (-w / 2, 0, 1), (0, 0, -length), (0, h, 0), "wall"),
        shapes.quad("right", (w / 2, 0, 1), (0, h, 0), (0, 0, -length), "wall"),
        shapes.quad("end", (-w / 2, 0, 1 - length), (w, 0, 0), (0, h, 0), "wall"),
    ]
    near = [((0.22, 1.45, -0.55), 0.06), ((-0.28, 1.3, -0.8), 0.08), ((0.35, 1.15, -1.0), 0.1)]  # targets "one"
    mid = [
        ((-0.6, 1.5, -1.6), 0.18),
        ((0.7, 1.0, -2.4), 0.22),
        ((-0.9, 1.7, -3.3), 0.25),
        ((0.9, 1.9, -4.2), 0.28),
        ((-0.3, 0.7, -5.0), 0.3),
    ]  # targets "two"
    for i, (c, r) in enumerate(near + mid):
        meshes.append(shapes.sphere(f"target_{i}", c, r, "target", subdivisions=5))
    meshes.append(shapes.sphere("big_blue_ball", (0.0, 1.2, -6.0), 0.8, "blue", subdivisions=5))
    crates = np.array([[-1.6, 0, -1.5], [1.2, 0, -3.0], [-1.4, 0, -4.5], [1.3, 0, -5.6]])
    meshes.append(shapes.boxes("crates", crates, crates + [0.5, 0.5, 0.5], "crate"))
    lights = [PointLight(position=(0.0, 2.8, -z), intensity=(3.0, 3.0, 3.0)) for z in (0.5, 4.0, 12.0)]
    return Scene(
        "shooting_range", meshes, mats, lights, ambient=(0.08, 0.08, 0.08), start=Pose.looking((0.0, 1.5, 0.0))
    )


def interior(ao_samples: int = 8, area_samples: int = 8) -> Scene:
    """A furnished room lit by a ceiling area light, with ambient occlusion."""
    mats = {
        "wall": Material(diffuse=(0.8, 0.78, 0.72)),
        "accent": Material(diffuse=(0.25, 0.4, 0.6)),
        "floor": Material(diffuse=(1, 1, 1), texture=Noise(colors=((0.35, 0.2, 0.1), (0.6, 0.4, 0.22)), scale=6.0)),
        "wood": Material(diffuse=(0.5, 0.32, 0.18), specular=0.1, shininess=16),
        "ceramic": Material(diffuse=(0.85, 0.85, 0.8), specular=0.4, shininess=96),
        "chrome": Material(diffuse=(0.05, 0.05, 0.05), specular=0.5, shininess=120, reflectance=0.7),
        "lamp": Material(diffuse=(0, 0, 0), emission=(6.0, 5.8, 5.2)),
    }
    meshes = [
        shapes.quad("floor", (-3, 0, 3), (6, 0, 0), (0, 0, -6), "floor", uv_scale=(6, 6)),
        shapes.quad("ceiling", (-3, 3, 3), (0, 0, -6), (6, 0, 0), "wall"),
        shapes.quad("back", (-3, 0, -3), (6, 0, 0), (0, 3, 0), "accent"),
        shapes.quad("front", (-3, 0, 3), (0, 3, 0), (6, 0, 0), "wall"),
        shapes.quad("left", (-3, 0, 3), (0, 0, -6), (0, 3, 0), "wall"),
        shapes.quad("right", (3, 0, 3), (0, 3, 0), (0, 0, -6), "wall"),
        shapes.box("table_top", (-0.8, 0.72, -1.6), (0.8, 0.78, -0.6), "wood"),
        shapes.boxes(
            "table_legs",
            np.array([[-0.75, 0, -1.55], [0.67, 0, -1.55], [-0.75, 0, -0.73], [0.67, 0, -0.73]]),
            np.array([[-0.67, 0.72, -1.47], [0.75, 0.72, -1.47], [-0.67, 0.72, -0.65], [0.75, 0.72, -0.65]]),
            "wood",
        ),
        shapes.box("shelf", (-2.9, 0, -2.9), (-1.6, 1.9, -2.4), "wood"),
        shapes.box("cabinet", (1.7, 0, -2.9), (2.9, 0.9, -2.2), "accent"),
        shapes.sphere("vase", (0.3, 0.93, -1.1), 0.15, "ceramic"),
        shapes.sphere("ball", (-0.35, 0.9, -1.2), 0.12, "chrome"),
        shapes.quad("lamp", (-0.6, 2.995, -0.6), (1.2, 0, 0), (0, 0, -1.2), "lamp"),
    ]
    lights = [
        AreaLight(
            corner=(-0.6, 2.99, -0.6),
            edge_u=(0.0, 0.0, -1.2),
            edge_v=(1.2, 0.0, 0.0),
            radiance=(6.0, 5.8, 5.2),
            samples=area_samples,
        )
    ]
    return Scene(
        "interior",
        meshes,
        mats,
        lights,
        ambient=(0.25, 0.25, 0.25),
        ao_samples=ao_samples,
        ao_distance=0.8,
        start=Pose.looking((0.0, 1.6, 2.2), 0.0, -12.0),
    )


def bunny() -> Scene:
    """The Stanford bunny on an irregular noise floor, with a mirror and a glass sphere."""
    import trimesh  # a second to import: only where a mesh is loaded (hmdrt.scene.shapes)

    with resources.as_file(resources.files("hmdrt.scene") / "data" / "bunny.ply") as path:
        raw = trimesh.load(path, process=True)
    scale = 6.0
    verts = np.asarray(raw.vertices) * scale
    verts += np.array([0.0, -verts[:, 1].min(), -2.6]) - [verts[:, 0].mean(), 0, verts[:, 2].mean()]
    mats = {
        "bunny": Material(diffuse=(0.8, 0.75, 0.7), specular=0.25, shininess=40),
        "floor": Material(
            diffuse=(1, 1, 1), texture=Noise(colors=((0.2, 0.3, 0.15), (0.75, 0.7, 0.55)), scale=1.5, octaves=6)
        ),
        "mirror": MIRROR,
        "glass": GLASS,
    }
    meshes = [
        Mesh("bunny", verts, np.asarray(raw.faces), "bunny", np.asarray(raw.vertex_normals, dtype=np.float64)),
        shapes.quad("floor", (-10, 0, 6), (20, 0, 0), (0, 0, -20), "floor", uv_scale=(20, 20)),
        shapes.sphere("mirror_sphere", (1.15, 0.45, -3.3), 0.45, "mirror"),
        shapes.sphere("glass_sphere", (-1.0, 0.3, -1.9), 0.3, "glass"),
    ]
    lights = [PointLight(position=(2.0, 5.0, 1.0), intensity=(30.0, 30.0, 30.0))]
    return _under_sky("bunny", meshes, mats, lights, Pose.looking((0.0, 1.2, 0.0), 0.0, -14.0))


BUILTINS: dict[str, Callable[..., Scene]] = {
    f.__name__: f for f in (whitted, tunnel_maps, tunnel_geom, voxel_city, shooting_range, interior, bunny)
}


# the triangles a built-in scene's size knobs make (voxel_city's on average): checked before it is built
TRIANGLES: dict[str, Callable[..., float]] = {
    "tunnel_maps": lambda length, section: 2 * MAPS_SEGMENTS * MAPS_RINGS * max(1.0, length / section),
    "tunnel_geom": lambda length, detail: 2 * GEOM_SEGMENTS * GEOM_RINGS_PER_M * length * detail**2,
    "voxel_city": lambda size: PLOT_TRIANGLES * size**2,
}
# the least value of each size knob: below it the scene is empty or not built
KNOB_MINIMA: dict[str, dict[str, float]] = {
    "tunnel_maps": {"length": 1.0, "section": 0.1},
    "tunnel_geom": {"length": 1.0, "detail": 1},
    "voxel_city": {"size": 1},
}


def builtin_parameters(name: str) -> dict[str, object]:
    """The knobs of a built-in scene and their defaults."""
    return {k: p.default for k, p in inspect.signature(BUILTINS[name]).parameters.items()}


def check_builtin_size(name: str, knobs: dict[str, object]) -> None:
    """A SceneError, before anything is built, where the built-in scene's size knobs (`knobs` and the defaults of
    the rest) make more triangles than MAX_SCENE_TRIANGLES."""
    if name not in TRIANGLES:
        return
    values = {**builtin_parameters(name), **knobs}
    size = {k: values[k] for k in inspect.signature(TRIANGLES[name]).parameters}
    try:
        triangles = TRIANGLES[name](**size)
    except OverflowError:  # a knob of hundreds of digits
        triangles = math.inf
    given = ", ".join(f"{k}={str(v)[:24]}" for k, v in size.items())  # a knob of many digits cut short
    refuse_large(f"scene {name!r} with {given} makes about", triangles, MAX_SCENE_TRIANGLES, "triangles", SceneError)
