"""kim21's stages beside full and Selective (reuse off), in one run, on a still view and the built-in head path.

    python bench/kim21_stages.py [--scene whitted] [--profile rift_s] [--frames 6] [--paths still builtin]

Frames are interleaved across the methods so that load on this shared machine hits all alike; figures are
medians over the frames after the first two (compilation, empty history). Per method: ms/frame (wall time
of render into a caller's buffer), each top-level stage's ms, "other" (render time outside any stage), rays per
frame, the overhead factor of issue 14 (ms per frame / the bare-embreex time of its rays, bare embreex timed on
the scene's primary rays on all threads in the same run) and the ms outside tracing (stages other than
presample and supersample). Selective is configs/eval/paper_tables.toml's (constant tau_fov, 4 samples in every
band) with reuse off, kim2021's comparison point.
"""

from __future__ import annotations

import argparse
import inspect
import os
import statistics
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from hmdrt.foveation import FrameRequest, make_method
from hmdrt.foveation.base import Method
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import load_scene
from hmdrt.scene.pack import pack
from hmdrt.sequence import builtin_path, eye_cameras, frame_requests
from hmdrt.telemetry.stats import RAY_KINDS, FrameStats
from hmdrt.trace.integrator import Whitted

SELECTIVE = "kim21?tau_0=1&tau_f=1&tau_f_slope=0&tau_np=1&n_f=4&n_p=4&n_m=4&n_np=4&reuse=false"
METHODS = {"full": "full", "kim21": "kim21", "selective": SELECTIVE}
TRACE_STAGES = {"presample", "supersample"}  # kim21's; full's stages are all the tracer's
TRACER_STAGES = {"raygen", "primary", "surface", "lightgen", "shadow", "area", "ao", "shade", "secondary", "gbuffer"}


def bare_rays_per_second(scene, camera: EyeCamera, repeats: int = 3) -> float:
    """bare embreex on the primary rays of one eye, split over all threads."""
    geometry = pack(scene).geometry
    dirs = camera.directions(pixel_centres(camera.width, camera.height))
    origins = np.empty_like(dirs)
    origins[:] = camera.position
    bare = rtcore_scene.EmbreeScene()
    TriangleMesh(bare, geometry.vertices, geometry.faces)
    threads = os.cpu_count() or 1
    parts = [slice(p[0], p[-1] + 1) for p in np.array_split(np.arange(len(dirs)), threads)]
    with ThreadPoolExecutor(threads) as pool:
        times = []
        for _ in range(repeats + 1):
            t = time.perf_counter()
            list(pool.map(lambda s: bare.run(origins[s], dirs[s], output=1), parts))
            times.append(time.perf_counter() - t)
    return len(dirs) / statistics.median(times[1:])


def requests(path: str, profile, scene, frames: int) -> list[FrameRequest]:
    if path == "still":
        camera = EyeCamera.for_eye(profile, scene.start)
        return [FrameRequest(camera, np.array([0.0, 0.0, -1.0]), f) for f in range(frames)]
    inputs = builtin_path(frames, profile.period_ns, scene.start)
    return [frame_requests(inp, eye_cameras(profile, inp.pose, ("left",)), 0)[0] for inp in inputs]


def compare(
    factories: dict[str, Callable[[Whitted], Method]], scene_name: str, profile_name: str, frames: int, paths: list[str]
) -> None:
    """Render every path with every method, frames interleaved, and print the medians."""
    scene = load_scene(scene_name)
    profile = get_profile(profile_name)
    rate = bare_rays_per_second(scene, EyeCamera.for_eye(profile, scene.start))
    print(f"{scene_name} at {profile_name} ({profile.width}x{profile.height}, one eye), bare {rate / 1e6:.1f} Mrays/s")
    out = np.empty((profile.height, profile.width, 3), np.float32)
    keep = slice(2, None) if frames > 2 else slice(None)
    with Whitted(scene) as tracer:
        for path in paths:
            reqs = requests(path, profile, scene, frames)
            methods = {name: make(tracer) for name, make in factories.items()}
            takes_out = {name: "out" in inspect.signature(m.render).parameters for name, m in methods.items()}
            wall: dict[str, list[float]] = {name: [] for name in methods}
            stages: dict[str, list[dict[str, float]]] = {name: [] for name in methods}
            rays: dict[str, list[int]] = {name: [] for name in methods}
            for req in reqs:
                for name, method in methods.items():
                    stats = FrameStats()
                    t = time.perf_counter()
                    method.render(req, stats, out) if takes_out[name] else method.render(req, stats)
                    wall[name].append((time.perf_counter() - t) * 1e3)
                    stages[name].append({k: v for k, v in stats.stages_ms.items() if "/" not in k})
                    rays[name].append(sum(stats.rays[k] for k in RAY_KINDS))
            print(f"\n{path}: median of frames {keep.start or 0}-{frames - 1}")
            ms = {}
            for name in methods:
                ms[name] = statistics.median(wall[name][keep])
                n_rays = statistics.median(rays[name][keep])
                names = dict.fromkeys(k for s in stages[name][keep] for k in s)
                per_stage = {k: statistics.median(s.get(k, 0.0) for s in stages[name][keep]) for k in names}
                outside = [w - sum(s.values()) for w, s in zip(wall[name][keep], stages[name][keep], strict=True)]
                other = statistics.median(outside)
                traced = TRACE_STAGES | TRACER_STAGES
                untraced = sum(v for k, v in per_stage.items() if k not in traced) + other
                factor = ms[name] / (n_rays / rate * 1e3)
                print(f"  {name:12s} {ms[name]:7.1f} ms  rays {n_rays / 1e6:5.2f}M  overhead x{factor:4.2f}", end="")
                print(f"  outside tracing {untraced:6.1f} ms")
                print("      " + "  ".join(f"{k} {v:.1f}" for k, v in per_stage.items()) + f"  other {other:.1f}")
            for name in ms:
                if name != "full" and "full" in ms:
                    print(f"  {name} / full = {ms[name] / ms['full']:.2f}")
            if "selective" in ms and "kim21" in ms:
                print(f"  selective / kim21 = {ms['selective'] / ms['kim21']:.2f} (kim2021: 1.5-5.3)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="whitted")
    ap.add_argument("--profile", default="rift_s")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--paths", nargs="+", default=["still", "builtin"], choices=["still", "builtin"])
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    args = ap.parse_args()
    factories = {name: (lambda tracer, spec=METHODS[name]: make_method(spec, tracer)) for name in args.methods}
    compare(factories, args.scene, args.profile, args.frames, args.paths)


if __name__ == "__main__":
    main()
