"""Rays per second of hmdrt's tracing path against a bare embreex call on the same rays, in one run.

    python bench/trace_throughput.py [--scene whitted] [--profile rift_s] [--repeats 7] [--rays N]

Measures, on the same primary rays of one eye (1280x1440 at rift_s; --rays: only the first N of them, the
size of a foveated method's batches, e.g. 4000 at sim-cpu):
  bare      one embreex EmbreeScene.run(..., output=1) call (one thread, as embreex offers it)
  bare-N    the same rays in parts that N pool threads take in turn (references.parts)
  tracer    hmdrt.trace.tracer.Tracer.intersect (Embree called from a numba kernel on the tracer's threads)
  primary   ray generation from the camera + Tracer.intersect (the project's whole primary path)
Repeats are interleaved and the median is reported, since these machines are shared and noisy.
The target is tracer / bare >= 0.85. On small batches bare-N shows what handing work to other
threads costs.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh
from references import parts

from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import load_scene
from hmdrt.scene.pack import pack
from hmdrt.trace.tracer import Tracer


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="whitted")
    ap.add_argument("--profile", default="rift_s")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--rays", type=int, default=0, help="trace only the first N primary rays (0: all)")
    args = ap.parse_args()

    scene = load_scene(args.scene)
    geometry = pack(scene).geometry
    profile = get_profile(args.profile)
    camera = EyeCamera.for_eye(profile, scene.start)
    rows = slice(0, -(-args.rays // profile.width) if args.rays else profile.height)

    def centres() -> np.ndarray:
        return pixel_centres(profile.width, profile.height, rows)[: args.rays or None]

    dirs = camera.directions(centres())
    origins = np.empty_like(dirs)
    origins[:] = camera.position
    n = len(dirs)

    bare = rtcore_scene.EmbreeScene()
    TriangleMesh(bare, geometry.vertices, geometry.faces)
    bare.run(origins[:1], dirs[:1])  # commit the BVH outside the timing
    threads = os.cpu_count() or 1
    pool = ThreadPoolExecutor(threads)
    tracer = Tracer(geometry)
    chunks = parts(n, threads)

    def run_bare() -> None:
        bare.run(origins, dirs, output=1)

    def run_bare_threads() -> None:
        list(pool.map(lambda s: bare.run(origins[s], dirs[s], output=1), chunks))

    def run_tracer() -> None:
        tracer.intersect(origins, dirs)

    def run_primary() -> None:
        d = camera.directions(centres())
        o = np.empty_like(d)
        o[:] = camera.position
        tracer.intersect(o, d)

    cases = {"bare": run_bare, f"bare-{threads}": run_bare_threads, "tracer": run_tracer, "primary": run_primary}
    for fn in cases.values():  # warm up caches, threads and numba
        fn()
    times: dict[str, list[float]] = {k: [] for k in cases}
    for _ in range(args.repeats):
        for name, fn in cases.items():
            t = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - t)
    tracer.close()
    pool.shutdown()

    rate = {k: n / statistics.median(v) for k, v in times.items()}
    print(
        f"{args.scene} at {args.profile}: {n:,} primary rays, {geometry.faces.shape[0]:,} triangles, "
        f"{threads} threads, median of {args.repeats}"
    )
    for name in cases:
        print(f"  {name:10s} {rate[name] / 1e6:7.2f} Mrays/s  ({statistics.median(times[name]) * 1e3:8.2f} ms)")
    ratio = rate["tracer"] / rate["bare"]
    target = f"  (target >= 0.85: {'met' if ratio >= 0.85 else 'NOT met'})" if not args.rays else ""
    print(f"ratio tracer / bare          = {ratio:.2f}{target}")
    same_threads = rate["tracer"] / rate[f"bare-{threads}"]
    print(f"ratio tracer / bare-{threads}        = {same_threads:.2f}  (overhead at equal parallelism)")
    print(f"ratio primary / bare         = {rate['primary'] / rate['bare']:.2f}  (with ray generation)")


if __name__ == "__main__":
    main()
