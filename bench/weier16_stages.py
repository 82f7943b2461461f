"""weier16's stages beside full, in one run: ms per frame and per stage, rays and the overhead factor.

    python bench/weier16_stages.py [--scenes whitted interior] [--profile rift_s] [--frames 8]
                                   [--views still head] [--methods full weier16] [--cpu]

Each scene is rendered on a still view (gaze ahead, head still) and on the built-in head path
(hmdrt.sequence.builtin_path), frames interleaved across methods so that load on this shared machine hits
all alike, each into a caller's image buffer where the method takes one. Figures are medians over the
frames after the first two (compilation, empty history). The overhead factor is ms per frame over the
bare-Embree time of the frame's rays at the rate embreex traces the scene's primary rays on every core
(issue 14). "own" sums a method's stages outside its "trace" stage (the tracer), listed after it.
--cpu: one numba thread and stage times in the main thread's CPU time (the tracer's Embree threads are
not counted), steadier than wall time when other processes share the cores.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from concurrent.futures import ThreadPoolExecutor
from inspect import signature

import numba
import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from hmdrt.foveation import FrameRequest, make_method
from hmdrt.foveation.base import Method
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.optics.profiles import HmdProfile
from hmdrt.scene import load_scene
from hmdrt.scene.pack import pack
from hmdrt.sequence import FrameInput, builtin_path
from hmdrt.spatial import gaze_direction
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted


def bare_rate(scene, camera: EyeCamera, repeats: int = 3) -> float:
    """Rays per second of bare embreex on the camera's primary rays, split over every core."""
    geometry = pack(scene).geometry
    dirs = camera.directions(pixel_centres(camera.width, camera.height))
    origins = np.empty_like(dirs)
    origins[:] = camera.position
    bare = rtcore_scene.EmbreeScene()
    TriangleMesh(bare, geometry.vertices, geometry.faces)
    parts = np.array_split(np.arange(len(dirs)), os.cpu_count() or 1)
    with ThreadPoolExecutor(len(parts)) as pool:
        run = lambda p: bare.run(origins[p[0] : p[-1] + 1], dirs[p[0] : p[-1] + 1], output=1)  # noqa: E731
        list(pool.map(run, parts))
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            list(pool.map(run, parts))
            times.append(time.perf_counter() - t)
    return len(dirs) / statistics.median(times)


def view_inputs(view: str, frames: int, profile: HmdProfile, scene) -> list[FrameInput]:
    if view == "head":
        return builtin_path(frames, profile.period_ns, scene.start)
    g = gaze_direction(0.0, 0.0)
    return [FrameInput(f, f * profile.period_ns, scene.start, {"left": g, "right": g}) for f in range(frames)]


def run_view(methods: dict[str, Method], profile: HmdProfile, inputs: list[FrameInput]) -> dict[str, list[FrameStats]]:
    """Per method, each frame's stats (stages_ms["frame"]: its whole render), frames interleaved."""
    out = np.empty((profile.height, profile.width, 3), np.float32)
    stats: dict[str, list[FrameStats]] = {spec: [] for spec in methods}
    for inp in inputs:
        camera = EyeCamera.for_eye(profile, inp.pose, "left")
        for spec, method in methods.items():
            s = FrameStats()
            request = FrameRequest(camera, inp.gaze["left"], inp.frame)
            into = (out,) if "out" in signature(method.render).parameters else ()  # not every method takes one yet
            t = time.perf_counter_ns()
            method.render(request, s, *into)
            s.stages_ms["frame"] = (time.perf_counter_ns() - t) / 1e6
            stats[spec].append(s)
    return stats


def report(spec: str, frames: list[FrameStats], rate: float, full_ms: float | None) -> str:
    """One method's line: medians of its frames after the first two."""
    kept = frames[2:] if len(frames) > 2 else frames

    def median(key: str) -> float:
        return statistics.median(f.stages_ms.get(key, 0.0) for f in kept)

    total, rays = median("frame"), statistics.median(sum(f.rays.values()) for f in kept)
    line = f"  {spec:14s} {total:7.1f} ms  rays {rays / 1e6:5.2f}M  overhead {total / (rays / rate * 1e3):5.2f}"
    if full_ms and spec != "full":
        line += f"  speed-up {full_ms / total:4.2f}x"
    if "trace" in kept[-1].stages_ms:
        own = [k for k in kept[-1].stages_ms if "/" not in k and k not in ("frame", "trace")]
        own_ms = statistics.median(sum(f.stages_ms.get(k, 0.0) for k in own) for f in kept)
        line += (
            f"  trace {median('trace'):6.1f}  own {own_ms:5.1f} ["
            + "  ".join(f"{k} {median(k):.1f}" for k in own)
            + "]"
        )
    return line


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["whitted", "interior"])
    ap.add_argument("--profile", default="rift_s")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--views", nargs="+", default=["still", "head"], choices=["still", "head"])
    ap.add_argument("--methods", nargs="+", default=["full", "weier16"])
    ap.add_argument("--cpu", action="store_true", help="one numba thread, stage times in main-thread CPU time")
    args = ap.parse_args()
    if args.cpu:
        numba.set_num_threads(1)
        time.perf_counter_ns = time.thread_time_ns  # FrameStats times stages with it

    profile = get_profile(args.profile)
    for name in args.scenes:
        scene = load_scene(name)
        rate = bare_rate(scene, EyeCamera.for_eye(profile, scene.start))
        with Whitted(scene) as tracer:
            for view in args.views:
                methods = {spec: make_method(spec, tracer) for spec in args.methods}
                stats = run_view(methods, profile, view_inputs(view, args.frames, profile, scene))
                full = statistics.median(f.stages_ms["frame"] for f in stats["full"][2:]) if "full" in stats else None
                print(
                    f"{name} {view} at {args.profile} ({profile.width}x{profile.height}), bare {rate / 1e6:.1f} Mrays/s"
                )
                for spec, frames in stats.items():
                    print(report(spec, frames, rate, full), flush=True)


if __name__ == "__main__":
    main()
