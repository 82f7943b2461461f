"""Every method's cost against the floor of the hardware, stage by stage, measured in one run.

    python bench/stage_budget.py [--scene whitted] [--profile rift_s] [--frames 8] [--warmup 2]
                                 [--trace builtin] [--gaze 0,0]
                                 [--methods full rrm weier16 weier18?dof=none weier18 kim21]

Two references are measured first, on this machine in this run: bare embreex on the scene's primary rays of the
whole image (EmbreeScene.run(..., output=1) on parts of them that as many pool threads as the tracer uses take in
turn, references.parts), and a numba copy of a 4-channel float32 image of the profile's size (the bandwidth one
fused image-space pass can reach). Then every method renders --frames frames interleaved across methods (the first
--warmup not counted), on a still view or the built-in head path, and for each method the bench prints its median
ms per frame, rays per frame, the bare-Embree time of those rays and its overhead factor (ms per frame over that
time; issue 14's target is <= 1.5). Beside it, the mix floor: the same rays at bare embreex's rate on rays of
their own kind from this view (references.bare_kind_rates: the mirror and glass spheres' secondary rays trace
several times slower than primary rays, bare or not), and the frame's time over that floor, which is what is left
to our own work. Last, the tracer: the ms of its own stages (meter.STAGES, wherever a method nests them) over the
bare time, the factor the method would reach if everything else it does took no time; above the target, the
method's rays bound it whatever its image work. Then each method's rays by kind, and every stage's median ms and,
where the stage says how many bytes it must touch (FrameStats.stage(..., touches=)), those bytes and what a copy
of them costs: a stage far above its copy time is where the next speed-up is.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections import defaultdict

import numpy as np
from references import bare_kind_rates, copy_rate, floor_ms, left_eye_requests

from hmdrt.foveation import make_method
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.trace.meter import STAGES as TRACER_STAGES

TARGET = 1.5
METHODS = ["full", "rrm", "weier16", "weier18?dof=none", "weier18", "kim21"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="whitted")
    ap.add_argument("--profile", default="rift_s")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--trace", choices=["builtin"], default=None, help="the built-in head path (default: still)")
    ap.add_argument("--gaze", default="0,0")
    ap.add_argument("--methods", nargs="+", default=METHODS)
    args = ap.parse_args()
    if args.frames <= args.warmup:
        ap.error("--frames must exceed --warmup")

    scene = load_scene(args.scene)
    profile = get_profile(args.profile)
    frames = left_eye_requests(scene, profile, args.frames, args.trace, args.gaze)
    threads = os.cpu_count() or 1
    kind_rates = bare_kind_rates(scene, frames[0].camera, threads)
    bare_rate = kind_rates["primary"]
    bytes_per_s = copy_rate(profile.width, profile.height)
    image_copy_ms = 2 * profile.width * profile.height * 16 / bytes_per_s * 1e3

    ms: dict[str, list[float]] = defaultdict(list)
    rays: dict[str, list[int]] = defaultdict(list)
    kinds: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
    floors: dict[str, list[float]] = defaultdict(list)
    own: dict[str, list[float]] = defaultdict(list)  # the tracer's own stages
    stages: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    touched: dict[str, dict[str, int]] = defaultdict(dict)
    with Whitted(scene, threads) as tracer:
        methods = {spec: make_method(spec, tracer) for spec in args.methods}
        outs = {spec: np.empty((profile.height, profile.width, 3), np.float32) for spec in methods}
        for k, request in enumerate(frames):
            for spec, method in methods.items():
                stats = FrameStats()
                t = time.perf_counter()
                method.render(request, stats, outs[spec])
                took = time.perf_counter() - t
                if k < args.warmup:
                    continue
                ms[spec].append(took * 1e3)
                rays[spec].append(sum(stats.rays.values()))
                for kind, count in stats.rays.items():
                    kinds[spec][kind].append(count)
                floors[spec].append(floor_ms(stats.rays, kind_rates))
                own[spec].append(sum(v for k, v in stats.stages_ms.items() if k.rsplit("/", 1)[-1] in TRACER_STAGES))
                for name, v in stats.stages_ms.items():
                    stages[spec][name].append(v)
                touched[spec].update(stats.touched)

    counted = args.frames - args.warmup
    print(
        f"{args.scene} at {args.profile} ({profile.width}x{profile.height}, one eye), "
        f"{'built-in head path' if args.trace else f'still view, gaze {args.gaze}'}, "
        f"{threads} threads, median of {counted} frames after {args.warmup}"
    )
    print(
        f"  bare embreex {bare_rate / 1e6:.1f} Mrays/s on primary rays; numba copy {bytes_per_s / 1e9:.1f} GB/s "
        f"(a {profile.width}x{profile.height}x4 float32 image read and written in {image_copy_ms:.2f} ms)"
    )
    measured = ", ".join(f"{kind} {rate / 1e6:.1f}" for kind, rate in kind_rates.items() if rate == rate)
    print(f"  bare embreex by kind of ray, Mrays/s: {measured}")
    print(
        f"  {'method':20s} {'ms/frame':>9s} {'rays/frame':>11s} {'bare ms':>8s} {'overhead':>9s}"
        f"          {'mix floor ms':>12s} {'over mix':>8s} {'tracer ms':>9s} {'tracer':>7s}"
    )
    for spec in methods:
        frame_ms = statistics.median(ms[spec])
        n = statistics.median(rays[spec])
        bare_ms = n / bare_rate * 1e3
        factor = frame_ms / bare_ms if bare_ms else float("inf")
        verdict = "ok" if factor <= TARGET else f"over {TARGET}"
        mix_ms = statistics.median(floors[spec])
        tracer_ms = statistics.median(own[spec])
        print(
            f"  {spec:20s} {frame_ms:9.1f} {int(n):11,d} {bare_ms:8.1f} {factor:8.2f}x  {verdict:9s}"
            f" {mix_ms:12.1f} {frame_ms / mix_ms:7.2f}x {tracer_ms:9.1f} {tracer_ms / bare_ms:6.2f}x"
        )
    for spec in methods:
        counts = ", ".join(f"{kind} {int(statistics.median(v)):,d}" for kind, v in kinds[spec].items() if any(v))
        print(f"\n  {spec}: rays per frame by kind, median: {counts}")
        print(f"  {spec}: stage, median ms (nested stages indented), MB touched, copy ms of those bytes, ratio")
        for name, values in stages[spec].items():
            depth = name.count("/")
            label = "  " * depth + name.rsplit("/", 1)[-1]
            line = f"    {label:28s} {statistics.median(values):9.2f}"
            nbytes = touched[spec].get(name)
            if nbytes:
                copy_ms = nbytes / bytes_per_s * 1e3
                line += f" {nbytes / 1e6:9.1f} {copy_ms:8.2f} {statistics.median(values) / copy_ms:7.1f}x"
            print(line)


if __name__ == "__main__":
    main()
