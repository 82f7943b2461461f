"""Every method's cost against the floor of the hardware, stage by stage, measured in one run.

    python bench/stage_budget.py [--scene whitted] [--profile rift_s] [--frames 8] [--warmup 2]
                                 [--trace builtin] [--gaze 0,0]
                                 [--methods SPEC ...]

Two references are timed on this machine in this run, once in every round of frames, right after it: bare
embreex on the scene's rays of each kind from the first frame's view (references.BareRays: EmbreeScene.run on
parts of them that as many pool threads as the tracer uses take in turn), and a numba copy of a 4-channel float32
image of the profile's size (the bandwidth one fused image-space pass can reach). Every method renders --frames
frames interleaved across methods (the first --warmup rounds not counted), on a still view or the built-in head
path, and each round's figures are set against the references of the same round, since these machines slow down
and speed up by 1.5-2x for minutes at a time; each ratio printed is the median of those rounds' ratios. For each
method the bench prints its median ms per frame, rays per frame, bare embreex's time for as many primary rays
and its overhead factor (ms per frame over that time; the target is at most 1.5). Beside it, the mix floor:
the same rays at bare embreex's rate on rays of their own kind (the mirror and glass spheres' secondary rays
trace several times slower than primary rays, bare or not), and the frame's time over that floor, which is what
is left to our own work. Last, the tracer: the ms of its own stages (meter.STAGES, wherever a method nests them)
over the bare time, the factor the method would reach if everything else it does took no time; above the target,
the method's rays bound it whatever its image work. With full among the methods, each one's ray ceiling: full's
mix floor over the method's, the most it could gain over full were both at bare embreex's rates and all else
free (what the speed-ups over full can reach on these rays). Then each method's rays by kind, and every
stage's median ms and, where the stage says how many bytes it must touch (FrameStats.stage(..., touches=)), those
bytes and what a copy of them costs: a stage far above its copy time is where the next speed-up is. The methods
are by default every registered one the benches time (default_methods: base.Checks.bench), with its variants.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections import defaultdict

import numpy as np
from references import BareRays, ImageCopy, floor_ms, frame_arguments, left_eye_requests, tracer_ms

from hmdrt.foveation import make_method
from hmdrt.foveation.registry import bench_methods
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

TARGET = 1.5


def default_methods() -> list[str]:
    """The specs timed without --methods: full, rrm, kim21, weier16, weier18 and weier18?dof=none, and any method
    registered since (registry.bench_methods)."""
    return bench_methods()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    frame_arguments(ap, 8, 2)
    ap.add_argument("--methods", nargs="+", default=default_methods())
    args = ap.parse_args()
    if args.frames <= args.warmup:
        ap.error("--frames must exceed --warmup")

    scene = load_scene(args.scene)
    profile = get_profile(args.profile)
    frames = left_eye_requests(scene, profile, args.frames, args.trace, args.gaze)
    threads = os.cpu_count() or 1
    image_copy = ImageCopy(profile.width, profile.height)

    rates: dict[str, list[float]] = defaultdict(list)  # per round, by kind of ray
    copy_rates: list[float] = []  # per round, bytes/s
    ms: dict[str, list[float]] = defaultdict(list)
    rays: dict[str, list[int]] = defaultdict(list)
    kinds: dict[str, dict[str, list[int]]] = defaultdict(lambda: defaultdict(list))
    bare: dict[str, list[float]] = defaultdict(list)  # the round's bare-embreex ms of the frame's rays
    floors: dict[str, list[float]] = defaultdict(list)
    own: dict[str, list[float]] = defaultdict(list)  # the tracer's own stages
    stages: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    copies: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))  # a copy of its bytes, ms
    touched: dict[str, dict[str, int]] = defaultdict(dict)
    with Whitted(scene, threads) as tracer, BareRays(scene, frames[0].camera, threads) as reference:
        methods = {spec: make_method(spec, tracer) for spec in args.methods}
        outs = {spec: np.empty((profile.height, profile.width, 3), np.float32) for spec in methods}
        for k, request in enumerate(frames):
            round_stats = {}
            for spec, method in methods.items():
                stats = FrameStats()
                t = time.perf_counter()
                method.render(request, stats, outs[spec])
                round_stats[spec] = (time.perf_counter() - t, stats)
            if k < args.warmup:
                continue
            round_rates, copy_rate = reference.rates(), image_copy.rate()  # beside the round's frames
            for kind, rate in round_rates.items():
                rates[kind].append(rate)
            copy_rates.append(copy_rate)
            for spec, (took, stats) in round_stats.items():
                ms[spec].append(took * 1e3)
                rays[spec].append(sum(stats.rays.values()))
                for kind, count in stats.rays.items():
                    kinds[spec][kind].append(count)
                bare[spec].append(rays[spec][-1] / round_rates["primary"] * 1e3)
                floors[spec].append(floor_ms(stats.rays, round_rates))
                own[spec].append(tracer_ms(stats))
                for name, v in stats.stages_ms.items():
                    stages[spec][name].append(v)
                    if stats.touched.get(name):
                        copies[spec][name].append(stats.touched[name] / copy_rate * 1e3)
                touched[spec].update(stats.touched)

    def spread(values: list[float], scale: float = 1.0) -> str:
        return f"{statistics.median(values) * scale:.1f} ({min(values) * scale:.1f}-{max(values) * scale:.1f})"

    def ratio(a: list[float], b: list[float]) -> float:
        """The median over the rounds of a / b: each round against the references timed beside it."""
        return statistics.median(x / y if y else float("inf") for x, y in zip(a, b, strict=True))

    counted = args.frames - args.warmup
    print(
        f"{args.scene} at {args.profile} ({profile.width}x{profile.height}, one eye), "
        f"{'built-in head path' if args.trace else f'still view, gaze {args.gaze}'}, "
        f"{threads} threads, median of {counted} rounds after {args.warmup}, the references timed in each round"
    )
    image_ms = [2 * profile.width * profile.height * 16 / r * 1e3 for r in copy_rates]
    print(
        f"  bare embreex {spread(rates['primary'], 1e-6)} Mrays/s on primary rays; numba copy "
        f"{spread(copy_rates, 1e-9)} GB/s (a {profile.width}x{profile.height}x4 float32 image read and written in "
        f"{spread(image_ms)} ms); median (lowest-highest) over the rounds"
    )
    measured = ", ".join(f"{kind} {spread(v, 1e-6)}" for kind, v in rates.items() if v[0] == v[0])
    print(f"  bare embreex by kind of ray, Mrays/s: {measured}")
    print(
        f"  {'method':20s} {'ms/frame':>9s} {'rays/frame':>11s} {'bare ms':>8s} {'overhead':>9s}"
        f"          {'mix floor ms':>12s} {'over mix':>8s} {'tracer ms':>9s} {'tracer':>7s}"
        + (f" {'ray ceiling':>11s}" if "full" in methods else "")
    )
    for spec in methods:
        factor = ratio(ms[spec], bare[spec])
        verdict = "ok" if factor <= TARGET else f"over {TARGET}"
        print(
            f"  {spec:20s} {statistics.median(ms[spec]):9.1f} {int(statistics.median(rays[spec])):11,d}"
            f" {statistics.median(bare[spec]):8.1f} {factor:8.2f}x  {verdict:9s}"
            f" {statistics.median(floors[spec]):12.1f} {ratio(ms[spec], floors[spec]):7.2f}x"
            f" {statistics.median(own[spec]):9.1f} {ratio(own[spec], bare[spec]):6.2f}x"
            + (f" {ratio(floors['full'], floors[spec]):10.2f}x" if "full" in methods else "")
        )
    for spec in methods:
        counts = ", ".join(f"{kind} {int(statistics.median(v)):,d}" for kind, v in kinds[spec].items() if any(v))
        print(f"\n  {spec}: rays per frame by kind, median: {counts}")
        print(f"  {spec}: stage, median ms (nested stages indented), MB touched, copy ms of those bytes, ratio")
        for name, values in stages[spec].items():
            depth = name.count("/")
            label = "  " * depth + name.rsplit("/", 1)[-1]
            line = f"    {label:28s} {statistics.median(values):9.2f}"
            copy = copies[spec].get(name)
            if copy:
                line += f" {touched[spec][name] / 1e6:9.1f} {statistics.median(copy):8.2f} {ratio(values, copy):7.1f}x"
            print(line)


if __name__ == "__main__":
    main()
