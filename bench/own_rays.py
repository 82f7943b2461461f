"""Bare embreex on each method's own rays against the view's, kind by kind, in one run: how much of a sparse method's
gap to its mix floor (bench/stage_budget.py) is the rays its sampling chose, not our own work.

    python bench/own_rays.py [--scene whitted] [--profile rift_s] [--frames 6] [--warmup 2] [--trace builtin]
                             [--gaze 0,0] [--rounds 9] [--methods SPEC ...]

stage_budget's mix floor prices a method's rays at bare embreex's rate on the view's rays of each kind: a camera ray
through every pixel centre, and the secondary and shadow rays of their hits, neighbours all. A foveated method
traces a sparse subset, whose neighbouring rays lie further apart, and Embree itself traces such rays slower. Each
method renders --frames frames, interleaved across methods; the samples of its last frame (every
Whitted.trace_samples call of that frame) become its own rays: camera rays through them, in the order the method
lists them, and their secondary and shadow rays built as references.BareRays builds the view's. Bare embreex then
traces the last frame's view and each method's own rays, alternating, --rounds times. The bench prints each kind's
rates and their ratio to the view's, and each method's median ms per frame (after --warmup) over its last frame's
rays priced at the view's rates (the mix floor) and at its own.
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections import defaultdict
from collections.abc import Callable

import numpy as np
from references import BareRays, floor_ms, frame_arguments, left_eye_requests

from hmdrt.evaluate.provenance import stamp
from hmdrt.foveation import make_method
from hmdrt.foveation.registry import bench_methods
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted


def default_methods() -> list[str]:
    """The specs timed without --methods: every method the benches time (registry.bench_methods)."""
    return bench_methods()


def record_samples(calls: list[np.ndarray]) -> Callable[[], None]:
    """Records the pixel coordinates of every Whitted.trace_samples call into `calls`; returns what puts the method
    back."""
    original = Whitted.trace_samples

    def recording(self, camera, xy, *args, **kwargs):
        calls.append(np.array(xy, np.float32))
        return original(self, camera, xy, *args, **kwargs)

    Whitted.trace_samples = recording
    return lambda: setattr(Whitted, "trace_samples", original)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    frame_arguments(ap, 6, 2)
    ap.add_argument("--rounds", type=int, default=9, help="timings of each set of rays, alternating")
    ap.add_argument("--methods", nargs="+", default=default_methods())
    args = ap.parse_args()
    if args.frames <= args.warmup:
        ap.error("--frames must exceed --warmup")

    scene, profile = load_scene(args.scene), get_profile(args.profile)
    frames = left_eye_requests(scene, profile, args.frames, args.trace, args.gaze)
    threads = os.cpu_count() or 1
    ms: dict[str, list[float]] = defaultdict(list)
    samples: dict[str, list[np.ndarray]] = defaultdict(list)  # the last frame's
    counts: dict[str, dict[str, int]] = {}  # the last frame's rays by kind
    with Whitted(scene, threads) as tracer:
        methods = {spec: make_method(spec, tracer) for spec in args.methods}
        out = np.empty((profile.height, profile.width, 3), np.float32)
        for k, request in enumerate(frames):
            last = k == len(frames) - 1
            for spec, method in methods.items():
                stats = FrameStats()
                undo = record_samples(samples[spec]) if last else None
                t = time.perf_counter()
                try:
                    method.render(request, stats, out)
                finally:
                    if undo:
                        undo()
                if k >= args.warmup:
                    ms[spec].append((time.perf_counter() - t) * 1e3)
                if last:
                    counts[spec] = dict(stats.rays)

    camera = frames[-1].camera
    view = BareRays(scene, camera, threads)
    traced = {spec: np.concatenate(xy) for spec, xy in samples.items() if sum(map(len, xy))}
    own = {spec: BareRays(scene, camera, threads, xy) for spec, xy in traced.items()}
    kinds = [kind for kind, rays in view.kinds.items() if rays is not None]
    rates: dict[str, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    try:
        for _ in range(args.rounds):
            for name, bare in (("view", view), *own.items()):
                for kind in kinds:
                    rates[name][kind].append(bare.rate(kind))
    finally:
        for bare in (view, *own.values()):
            bare.close()
    median = {name: {kind: statistics.median(v) for kind, v in by_kind.items()} for name, by_kind in rates.items()}

    where = stamp()
    print(
        f"{args.scene} at {args.profile} ({profile.width}x{profile.height}, one eye), "
        f"{'built-in head path' if args.trace else f'still view, gaze {args.gaze}'}: each method's rays of frame "
        f"{args.frames}, bare embreex on {threads} threads, median of {args.rounds} rounds, alternating: "
        f"{where['date']}, {where['commit']}, {where['machine']}"
    )
    print("  the view's rays, Mrays/s: " + ", ".join(f"{k} {median['view'][k] / 1e6:.1f}" for k in kinds))
    print(f"  {'method':20s} {'samples':>9s}  own rays, Mrays/s (x the view's rate)")
    for spec in own:
        rays = ", ".join(
            f"{kind} {median[spec][kind] / 1e6:.1f} ({median[spec][kind] / median['view'][kind]:.2f})"
            for kind in kinds
            if median[spec][kind] == median[spec][kind]  # nan: the method's rays have none of that kind
        )
        print(f"  {spec:20s} {len(traced[spec]):9,d}  {rays}")
    for spec in sorted(set(methods) - set(own)):
        print(f"  {spec:20s} {0:9,d}  (no rays in its last frame)")
    print(
        f"\n  {'method':20s} {'ms/frame':>9s} {'mix floor ms':>12s} {'over mix':>8s}"
        f" {'own floor ms':>12s} {'over own':>8s}  (the last frame's rays at the view's rates and at its own)"
    )
    for spec in own:
        # a kind none of the method's hits spawned at depth 1 (deeper ones may have) at the view's rate
        own_rates = {k: r if r == r else median["view"][k] for k, r in median[spec].items()}
        frame, mix, floor = (
            statistics.median(ms[spec]),
            floor_ms(counts[spec], median["view"]),
            floor_ms(counts[spec], own_rates),
        )
        print(f"  {spec:20s} {frame:9.1f} {mix:12.1f} {frame / mix:7.2f}x {floor:12.1f} {frame / floor:7.2f}x")


if __name__ == "__main__":
    main()
