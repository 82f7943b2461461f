"""Each method's speed-up over full, with its error against the 36-spp ground truth, in one run.

    python bench/foveation_speedup.py [--scene whitted] [--profile rift_s] [--frames 14] [--gaze 0,0]
                                      [--trace builtin] [--methods SPEC ...]

A still view with a fixed gaze (or, with --trace builtin, the built-in head path: head sway, fixations and
saccades) is rendered for --frames frames by every method, frames interleaved across methods so that load
on this shared machine hits all alike. ms per frame is the median of the frames after the first two
(compilation, empty history); the speed-up is full's median over the method's, and its ceiling full's median
over the method's tracer alone (the median of its tracer's own stages, meter.STAGES, wherever it nests them):
the speed-up it would reach if all its other work took no time, which its rays bound. The mean of the same frames
and full's mean over the method's show work that comes every few frames, which the median passes over: kim21
re-traces every central pixel whose reuse has run out (n_reuse_max), on a still view all of them every sixth
frame. PSNR (dB) is of the last
frame against regular with 36 stratified samples per pixel (the ground truth of kim2021) of that frame's
view, in the foveal band (eccentricity < 3.3 deg) and over the whole image. RRM needs N = 12 frames to
refresh its whole periphery, hence 14 frames by default. The methods are by default every registered one the benches
time (default_methods: base.Checks.bench), with its variants.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
from references import frame_arguments, left_eye_requests, tracer_ms

from hmdrt.evaluate.quality import band_psnr
from hmdrt.foveation import make_method
from hmdrt.foveation.registry import bench_methods
from hmdrt.optics import get_profile
from hmdrt.optics.camera import eccentricity_map
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted


def default_methods() -> list[str]:
    """The specs timed without --methods: full, rrm, kim21, weier16, weier18 and weier18?dof=none, and any method
    registered since (registry.bench_methods)."""
    return bench_methods()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    frame_arguments(ap, 14)
    ap.add_argument("--methods", nargs="+", default=default_methods())
    args = ap.parse_args()

    scene = load_scene(args.scene)
    profile = get_profile(args.profile)
    requests = left_eye_requests(scene, profile, args.frames, args.trace, args.gaze)
    last_request = requests[-1]
    ecc = eccentricity_map(last_request.camera, last_request.gaze)
    with Whitted(scene) as tracer:
        t = time.perf_counter()
        truth = make_method("regular?spp=36", tracer).render(last_request, FrameStats())
        truth_s = time.perf_counter() - t
        methods = {spec: make_method(spec, tracer) for spec in args.methods}
        outs = {spec: np.empty((profile.height, profile.width, 3), np.float32) for spec in methods}
        times: dict[str, list[float]] = {spec: [] for spec in methods}
        tracer: dict[str, list[float]] = {spec: [] for spec in methods}  # its tracer's own ms
        rays: dict[str, int] = {}
        for request in requests:
            for spec, method in methods.items():
                stats = FrameStats()
                t = time.perf_counter()
                method.render(request, stats, outs[spec])
                times[spec].append(time.perf_counter() - t)
                tracer[spec].append(tracer_ms(stats))
                rays[spec] = sum(stats.rays.values())

    def kept(values: list[float]) -> list[float]:
        return values[2:] if len(values) > 2 else values

    def counted(values: list[float]) -> float:
        return statistics.median(kept(values))

    ms = {spec: counted(v) * 1e3 for spec, v in times.items()}
    mean = {spec: statistics.fmean(kept(v)) * 1e3 for spec, v in times.items()}
    traced = {spec: counted(v) for spec, v in tracer.items()}
    base, base_mean = ms.get("full"), mean.get("full")
    print(
        f"{args.scene} at {args.profile} ({profile.width}x{profile.height}, one eye), "
        f"{'built-in head path' if args.trace else f'still view, gaze {args.gaze}'}, "
        f"{args.frames} frames, median (and mean) ms/frame after frame 2; truth: regular 36 spp ({truth_s:.1f} s)"
    )
    print(
        f"  {'method':28s} {'ms/frame':>9s} {'speed-up':>9s} {'tracer ms':>9s} {'ceiling':>8s} {'rays/frame':>11s}"
        f" {'fovea dB':>9s} {'image dB':>9s} {'mean ms':>9s} {'on means':>9s}"
    )
    for spec in methods:
        psnr = band_psnr(outs[spec], truth, ecc)
        speedup = f"{base / ms[spec]:8.2f}x" if base else "-"
        ceiling = f"{base / traced[spec]:7.2f}x" if base and traced[spec] else "-"
        on_means = f"{base_mean / mean[spec]:8.2f}x" if base_mean else "-"
        print(
            f"  {spec:28s} {ms[spec]:9.1f} {speedup:>9s} {traced[spec]:9.1f} {ceiling:>8s} {rays[spec]:11,d}"
            f" {psnr['fovea']:9.1f} {psnr['image']:9.1f} {mean[spec]:9.1f} {on_means:>9s}"
        )


if __name__ == "__main__":
    main()
