"""Each method's speed-up over full, with its error against the 36-spp ground truth, in one run.

    python bench/foveation_speedup.py [--scene whitted] [--profile rift_s] [--frames 14] [--gaze 0,0]
                                      [--methods full rrm kim21 weier16 weier18]

A still view with a fixed gaze is rendered for --frames frames by every method, frames interleaved
across methods so that load on this shared machine hits all alike. ms per frame is the median of the
frames after the first two (compilation, empty history); the speed-up is full's median over the
method's. PSNR (dB) is of the last frame against regular with 36 stratified samples per pixel (the
ground truth of kim2021), in the foveal band (eccentricity < 3.3 deg) and over the whole image.
RRM needs N = 12 frames to refresh its whole periphery, hence 14 frames by default.
"""

from __future__ import annotations

import argparse
import statistics
import time

from hmdrt.foveation import FrameRequest, make_method
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.quality import band_psnr
from hmdrt.scene import load_scene
from hmdrt.spatial import gaze_direction, parse_gaze
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="whitted")
    ap.add_argument("--profile", default="rift_s")
    ap.add_argument("--frames", type=int, default=14)
    ap.add_argument("--gaze", default="0,0")
    ap.add_argument("--methods", nargs="+", default=["full", "rrm", "kim21", "weier16", "weier18"])
    args = ap.parse_args()

    scene = load_scene(args.scene)
    profile = get_profile(args.profile)
    gaze = gaze_direction(*parse_gaze(args.gaze))
    camera = EyeCamera.for_eye(profile, scene.start)
    ecc = camera.eccentricity(gaze)
    with Whitted(scene) as tracer:
        t = time.perf_counter()
        truth = make_method("regular?spp=36", tracer).render(FrameRequest(camera, gaze), FrameStats())
        truth_s = time.perf_counter() - t
        methods = {spec: make_method(spec, tracer) for spec in args.methods}
        times: dict[str, list[float]] = {spec: [] for spec in methods}
        rays: dict[str, int] = {}
        last = {}
        for frame in range(args.frames):
            for spec, method in methods.items():
                stats = FrameStats()
                t = time.perf_counter()
                image = method.render(FrameRequest(camera, gaze, frame), stats)
                times[spec].append(time.perf_counter() - t)
                rays[spec] = (
                    stats.rays["primary"]
                    + stats.rays["shadow"]
                    + stats.rays["secondary"]
                    + stats.rays["ao"]
                    + stats.rays["area"]
                )
                last[spec] = image.copy()

    ms = {spec: statistics.median(v[2:] if len(v) > 2 else v) * 1e3 for spec, v in times.items()}
    base = ms.get("full")
    print(
        f"{args.scene} at {args.profile} ({profile.width}x{profile.height}, one eye), gaze {args.gaze}, "
        f"{args.frames} frames, median ms/frame after frame 2; truth: regular 36 spp ({truth_s:.1f} s)"
    )
    print(f"  {'method':28s} {'ms/frame':>9s} {'speed-up':>9s} {'rays/frame':>11s} {'fovea dB':>9s} {'image dB':>9s}")
    for spec in methods:
        psnr = band_psnr(last[spec], truth, ecc)
        speedup = f"{base / ms[spec]:8.2f}x" if base else "        -"
        print(f"  {spec:28s} {ms[spec]:9.1f} {speedup:>9s} {rays[spec]:11,d} {psnr['fovea']:9.1f} {psnr['image']:9.1f}")


if __name__ == "__main__":
    main()
