"""What the benches measure against, in the same run: bare embreex's rays per second, a numba copy's bytes
per second, and the frames a bench renders (a still view or the built-in head path)."""

from __future__ import annotations

import statistics
import time
from concurrent.futures import ThreadPoolExecutor

import numba as nb
import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from hmdrt.foveation import FrameRequest
from hmdrt.jit import kernel
from hmdrt.optics import EyeCamera, HmdProfile
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import Scene
from hmdrt.scene.pack import pack
from hmdrt.sequence import eye_cameras, frame_requests, sequence_inputs


@kernel
def _copy(src, dst):
    for i in nb.prange(src.shape[0]):
        for j in range(src.shape[1]):
            dst[i, j] = src[i, j]


def copy_rate(width: int, height: int, repeats: int = 15) -> float:
    """Bytes per second (read + write) of a parallel numba copy of a (height * width, 4) float32 image."""
    src = np.random.default_rng(0).random((width * height, 4), dtype=np.float32)
    dst = np.empty_like(src)
    _copy(src, dst)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        _copy(src, dst)
        times.append(time.perf_counter() - t)
    return 2 * src.nbytes / statistics.median(times)


PARTS_PER_THREAD = 32  # a thread takes the next part when it is free: rays differ in cost across the image
MIN_PART = 16384  # rays: a call's own cost (~0.1 ms) stays within a few percent of its part's


def parts(n: int, threads: int) -> list[slice]:
    """n rays in PARTS_PER_THREAD x `threads` equal parts of MIN_PART rays at least, for `threads` pool threads to
    take in turn as each frees up (as hmdrt's tracer claims its blocks: hmdrt.schedule); equal halves would
    leave one thread idle while the other traces the costlier half of the image."""
    count = max(threads, min(threads * PARTS_PER_THREAD, n // MIN_PART))
    return [slice(p[0], p[-1] + 1) for p in np.array_split(np.arange(n), count) if len(p)]


def _timed_rate(bare, origins, dirs, threads: int, repeats: int, dists=None, query: str = "INTERSECT") -> float:
    """Rays per second of bare embreex on these rays, their parts() traced on `threads` pool threads."""
    if len(dirs) == 0:
        return float("nan")
    parts_ = parts(len(dirs), threads)
    times = []
    with ThreadPoolExecutor(threads) as pool:
        for _ in range(repeats):
            t = time.perf_counter()
            if query == "INTERSECT":
                list(pool.map(lambda s: bare.run(origins[s], dirs[s], output=1), parts_))
            else:
                list(pool.map(lambda s: bare.run(origins[s], dirs[s], dists[s], query=query), parts_))
            times.append(time.perf_counter() - t)
    return len(dirs) / statistics.median(times)


def _embree(scene: Scene):
    packed = pack(scene)
    bare = rtcore_scene.EmbreeScene()
    TriangleMesh(bare, packed.geometry.vertices, packed.geometry.faces)
    return packed, bare


def _primary_rays(camera: EyeCamera) -> tuple[np.ndarray, np.ndarray]:
    dirs = camera.directions(pixel_centres(camera.width, camera.height))
    origins = np.empty_like(dirs)
    origins[:] = camera.position
    return origins, dirs


def _unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def bare_kind_rates(scene: Scene, camera: EyeCamera, threads: int, repeats: int = 3) -> dict[str, float]:
    """Bare embreex's rays per second on each kind of ray the tracer casts (meter.RAY_KINDS), built from this
    view: primary (the camera's rays), secondary (the mirror reflections and refractions at the first hits on
    reflective or transmissive surfaces), shadow (each first hit to each point light), area (to a random point
    of each area light) and ao (cosine-distributed within the scene's ao_distance); occlusion queries for the
    last three. A kind the view has none of is nan. The floor of a method's frame is its rays of each kind at
    these rates: what the scene's rays cost before any of our own work."""
    packed, bare = _embree(scene)
    origins, dirs = _primary_rays(camera)
    bare.run(origins[:1], dirs[:1])  # commit the BVH outside the timing
    rates = {"primary": _timed_rate(bare, origins, dirs, threads, repeats)}
    first = bare.run(origins, dirs, output=1)
    hit = first["primID"] >= 0
    prim, t = first["primID"][hit], first["tfar"][hit]
    geo, mats, lights = packed.geometry, packed.materials, packed.lights
    normal = geo.face_normals[prim].astype(np.float64)
    d = dirs[hit].astype(np.float64)
    normal[(normal * d).sum(1) > 0] *= -1  # facing the ray
    point = origins[hit] + d * t[:, None]
    eps = 1e-4 * np.maximum(1.0, np.abs(point).max(axis=1, keepdims=True))
    above = (point + normal * eps).astype(np.float32)
    material = geo.object_material[geo.tri_object[prim]]
    cos_i = -(d * normal).sum(1, keepdims=True)
    reflective = mats.reflectance[material] > 0
    transmissive = mats.transmittance[material] > 0
    eta = 1.0 / mats.ior[material][:, None]
    k = 1.0 - eta**2 * (1.0 - cos_i**2)
    refracts = transmissive & (k[:, 0] > 0)
    refracted = eta * d + (eta * cos_i - np.sqrt(np.maximum(k, 0.0))) * normal
    sec_o = np.concatenate([above[reflective], (point - normal * eps).astype(np.float32)[refracts]])
    sec_d = np.concatenate([_unit((d + 2 * cos_i * normal)[reflective]), _unit(refracted[refracts])])
    rates["secondary"] = _timed_rate(bare, sec_o, sec_d, threads, repeats)
    rng = np.random.default_rng(0)

    def occluded_rate(targets: list[np.ndarray]) -> float:
        if not targets:
            return float("nan")
        to = np.concatenate([target - point for target in targets])
        dist = np.linalg.norm(to, axis=1)
        o = np.concatenate([above] * len(targets))
        return _timed_rate(bare, o, _unit(to), threads, repeats, (dist * 0.999).astype(np.float32), "OCCLUDED")

    rates["shadow"] = occluded_rate([np.broadcast_to(p, point.shape) for p in lights.point_position])
    corners = [
        c + rng.random((len(point), 1)) * u + rng.random((len(point), 1)) * v
        for c, u, v in zip(lights.area_corner, lights.area_u, lights.area_v, strict=True)
    ]
    rates["area"] = occluded_rate(corners)
    if scene.ao_samples:
        tangent = _unit(np.cross(normal, np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])))
        bitangent = np.cross(normal, tangent)
        u1, u2 = rng.random((2, len(point), 1))
        r, phi = np.sqrt(u1), 2 * np.pi * u2
        ao_dir = _unit(r * np.cos(phi) * tangent + r * np.sin(phi) * bitangent + np.sqrt(1 - u1) * normal)
        far = np.full(len(point), scene.ao_distance, np.float32)
        rates["ao"] = _timed_rate(bare, above, ao_dir, threads, repeats, far, "OCCLUDED")
    else:
        rates["ao"] = float("nan")
    return rates


def floor_ms(rays: dict[str, float], rates: dict[str, float]) -> float:
    """The bare-embreex time of a frame's rays by kind at `rates` (bare_kind_rates)."""
    return sum(n / rates[kind] * 1e3 for kind, n in rays.items() if n)


def left_eye_requests(
    scene: Scene, profile: HmdProfile, frames: int, trace: str | None, gaze: str = "0,0"
) -> list[FrameRequest]:
    """The left eye's frame requests: a fixed gaze with the head still (trace None), or the built-in head path."""
    inputs, _ = sequence_inputs(scene.start, profile.period_ns, frames, trace, gaze)
    return [frame_requests(inp, eye_cameras(profile, inp.pose, ("left",)), 0)[0] for inp in inputs]
