"""Stereo frame time of a method on every built-in scene, against the refresh period of a profile.

    python bench/frame_budget.py [--profile sim-cpu] [--method full] [--frames 8]

Renders both eyes per frame (as the compositor will), reports the median over frames after two
warm-up frames, and the share of the profile's VSync period it uses. This is the measurement
behind docs/performance.md's statement of what the sim-cpu profile holds on this machine.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from hmdrt.foveation import FrameRequest, make_method
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.scene import BUILTINS, load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--profile", default="sim-cpu")
    ap.add_argument("--method", default="full")
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--scenes", nargs="*", default=list(BUILTINS))
    args = ap.parse_args()
    profile = get_profile(args.profile)
    period_ms = 1e3 / profile.refresh_hz
    print(
        f"{args.method} at {args.profile} ({profile.width}x{profile.height} per eye, both eyes, "
        f"{profile.refresh_hz:g} Hz = {period_ms:.1f} ms budget), median of {args.frames} frames"
    )
    gaze = np.array([0.0, 0.0, -1.0])
    for name in args.scenes:
        scene = load_scene(name)
        with Whitted(scene) as tracer:
            method = make_method(args.method, tracer)
            cams = [EyeCamera.for_eye(profile, scene.start, eye) for eye in ("left", "right")]
            times = []
            for frame in range(args.frames + 2):
                t = time.perf_counter()
                for cam in cams:
                    method.render(FrameRequest(cam, gaze, frame), FrameStats())
                times.append(time.perf_counter() - t)
        ms = statistics.median(times[2:]) * 1e3
        print(
            f"  {name:15s} {ms:7.1f} ms  {ms / period_ms:6.0%} of the period  {'holds' if ms < period_ms else 'misses'}"
        )


if __name__ == "__main__":
    main()
