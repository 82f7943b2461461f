"""What the benches measure against, in the same run: bare embreex's rays per second, a numba copy's bytes
per second, and the frames a bench renders (a still view or the built-in head path)."""

from __future__ import annotations

import argparse
import importlib.util
import statistics
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import ModuleType
from typing import NamedTuple

import numba as nb
import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from hmdrt.foveation import FrameRequest
from hmdrt.kernels.jit import kernel
from hmdrt.optics import EyeCamera, HmdProfile
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import Scene
from hmdrt.scene.pack import pack
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.meter import STAGES as TRACER_STAGES
from hmdrt.views import eye_cameras, frame_requests, sequence_inputs


@kernel
def copy_rows(src: np.ndarray, dst: np.ndarray) -> None:
    """dst[:] = src for 2-D arrays, one numba pass: the floor of any pass that reads and writes them."""
    for i in nb.prange(src.shape[0]):
        for j in range(src.shape[1]):
            dst[i, j] = src[i, j]


ROOT = Path(__file__).resolve().parents[1]


def module_at(revision: str, path: str, folder: Path) -> ModuleType:
    """The module at `path` (in the repository) as it was at git `revision`, imported from a copy in `folder`, to be
    timed beside the current one in the same run."""
    source = subprocess.run(["git", "show", f"{revision}:{path}"], cwd=ROOT, capture_output=True, text=True, check=True)
    name = f"{Path(path).stem}_at_{revision}"
    copy = folder / f"{name}.py"
    copy.write_text(source.stdout, encoding="utf-8")
    spec = importlib.util.spec_from_file_location(name, copy)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module  # numba's cache and dataclasses look the module up by name
    spec.loader.exec_module(module)
    return module


class ImageCopy:
    """A parallel numba copy of a (height * width, 4) float32 image, the bandwidth one fused image-space pass can
    reach, timed as often as a bench asks (rate)."""

    def __init__(self, width: int, height: int):
        self._src = np.random.default_rng(0).random((width * height, 4), dtype=np.float32)
        self._dst = np.empty_like(self._src)
        copy_rows(self._src, self._dst)

    def rate(self, repeats: int = 5) -> float:
        """Bytes per second (read + write), the median of `repeats` copies."""
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            copy_rows(self._src, self._dst)
            times.append(time.perf_counter() - t)
        return 2 * self._src.nbytes / statistics.median(times)


PARTS_PER_THREAD = 32  # a thread takes the next part when it is free: rays differ in cost across the image
MIN_PART = 16384  # rays: a call's own cost (~0.1 ms) stays within a few percent of its part's


def parts(n: int, threads: int) -> list[slice]:
    """n rays in PARTS_PER_THREAD x `threads` equal parts of MIN_PART rays at least, for `threads` pool threads to
    take in turn as each frees up (as hmdrt's tracer claims its blocks: hmdrt.kernels.schedule); equal halves would
    leave one thread idle while the other traces the costlier half of the image."""
    count = max(threads, min(threads * PARTS_PER_THREAD, n // MIN_PART))
    return [slice(p[0], p[-1] + 1) for p in np.array_split(np.arange(n), count) if len(p)]


class _Kind(NamedTuple):
    """One kind of ray of a view, ready for bare embreex: intersections (dists None) or occlusion queries."""

    origins: np.ndarray
    dirs: np.ndarray
    dists: np.ndarray | None


class BareRays:
    """Bare embreex on each kind of ray the tracer casts (meter.RAY_KINDS), built from one view: primary (the
    camera's rays), secondary (the mirror reflections and refractions at the first hits on reflective or
    transmissive surfaces), shadow (each first hit to each point light), area (to a random point of each area
    light) and ao (cosine-distributed within the scene's ao_distance); occlusion queries for the last three.
    The rays are built once and timed as often as a bench asks (rates), on `threads` pool threads taking their
    parts() in turn: a bench that times them beside each round of its frames sets each round against what the
    machine ran at just then, since these machines slow down and speed up by 1.5-2x for minutes at a time. The
    floor of a method's frame is its rays of each kind at these rates: what the scene's rays cost before any of
    our own work. `xy`: the camera rays' pixel coordinates (n, 2), in their order; by default every pixel centre."""

    def __init__(self, scene: Scene, camera: EyeCamera, threads: int, xy: np.ndarray | None = None):
        packed, self._bare = _embree(scene)
        self._pool = ThreadPoolExecutor(threads)
        self._threads = threads
        origins, dirs = _primary_rays(camera, pixel_centres(camera.width, camera.height) if xy is None else xy)
        self._bare.run(origins[:1], dirs[:1])  # commit the BVH outside the timing
        self.kinds: dict[str, _Kind | None] = {"primary": _Kind(origins, dirs, None)}
        first = self._bare.run(origins, dirs, output=1)
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
        self.kinds["secondary"] = _Kind(sec_o, sec_d, None) if len(sec_d) else None
        rng = np.random.default_rng(0)

        def occlusion(targets: list[np.ndarray]) -> _Kind | None:
            if not targets:
                return None
            to = np.concatenate([target - point for target in targets])
            dist = np.linalg.norm(to, axis=1)
            o = np.concatenate([above] * len(targets))
            return _Kind(o, _unit(to), (dist * 0.999).astype(np.float32))

        self.kinds["shadow"] = occlusion([np.broadcast_to(p, point.shape) for p in lights.point_position])
        corners = [
            c + rng.random((len(point), 1)) * u + rng.random((len(point), 1)) * v
            for c, u, v in zip(lights.area_corner, lights.area_u, lights.area_v, strict=True)
        ]
        self.kinds["area"] = occlusion(corners)
        self.kinds["ao"] = None
        if scene.ao_samples:
            tangent = _unit(np.cross(normal, np.where(np.abs(normal[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])))
            bitangent = np.cross(normal, tangent)
            u1, u2 = rng.random((2, len(point), 1))
            r, phi = np.sqrt(u1), 2 * np.pi * u2
            ao_dir = _unit(r * np.cos(phi) * tangent + r * np.sin(phi) * bitangent + np.sqrt(1 - u1) * normal)
            self.kinds["ao"] = _Kind(above, ao_dir, np.full(len(point), scene.ao_distance, np.float32))

    def rate(self, kind: str, repeats: int = 1) -> float:
        """Rays per second of bare embreex on this view's rays of `kind` (the median of `repeats` timings), nan for
        a kind the view has none of."""
        rays = self.kinds[kind]
        if rays is None:
            return float("nan")
        o, d, far = rays
        parts_ = parts(len(d), self._threads)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            if far is None:
                list(self._pool.map(lambda s: self._bare.run(o[s], d[s], output=1), parts_))
            else:
                list(self._pool.map(lambda s: self._bare.run(o[s], d[s], far[s], query="OCCLUDED"), parts_))
            times.append(time.perf_counter() - t)
        return len(d) / statistics.median(times)

    def rates(self, repeats: int = 1) -> dict[str, float]:
        """rate() of every kind."""
        return {kind: self.rate(kind, repeats) for kind in self.kinds}

    def close(self) -> None:
        self._pool.shutdown()

    def __enter__(self) -> BareRays:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _embree(scene: Scene):
    packed = pack(scene)
    bare = rtcore_scene.EmbreeScene()
    TriangleMesh(bare, packed.geometry.vertices, packed.geometry.faces)
    return packed, bare


def _primary_rays(camera: EyeCamera, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    dirs = camera.directions(xy)
    origins = np.empty_like(dirs)
    origins[:] = camera.position
    return origins, dirs


def _unit(v: np.ndarray) -> np.ndarray:
    return (v / np.linalg.norm(v, axis=1, keepdims=True)).astype(np.float32)


def tracer_ms(stats: FrameStats) -> float:
    """A frame's ms in the tracer's own stages (meter.STAGES), wherever the method nests them."""
    return sum(v for k, v in stats.stages_ms.items() if k.rsplit("/", 1)[-1] in TRACER_STAGES)


def floor_ms(rays: dict[str, float], rates: dict[str, float]) -> float:
    """The bare-embreex time of a frame's rays by kind at `rates` (BareRays.rates)."""
    return sum(n / rates[kind] * 1e3 for kind, n in rays.items() if n)


def frame_arguments(ap: argparse.ArgumentParser, frames: int, warmup: int | None = None) -> None:
    """The options of a bench that renders one eye's frames of a method (left_eye_requests): --scene, --profile,
    --frames, --warmup (where the bench leaves warm-up frames out), --trace and --gaze."""
    ap.add_argument("--scene", default="whitted")
    ap.add_argument("--profile", default="rift_s")
    ap.add_argument("--frames", type=int, default=frames)
    if warmup is not None:
        ap.add_argument("--warmup", type=int, default=warmup)
    ap.add_argument("--trace", choices=["builtin"], default=None, help="the built-in head path (default: still)")
    ap.add_argument("--gaze", default="0,0")


def left_eye_requests(
    scene: Scene, profile: HmdProfile, frames: int, trace: str | None, gaze: str = "0,0"
) -> list[FrameRequest]:
    """The left eye's frame requests: a fixed gaze with the head still (trace None), or the built-in head path."""
    inputs, _ = sequence_inputs(scene.start, profile.period_ns, frames, trace, gaze)
    return [frame_requests(inp, eye_cameras(profile, inp.pose, ("left",)), 0)[0] for inp in inputs]
