"""Milliseconds of rotational timewarp (hmdrt.present.timewarp) for both eyes at sim-cpu-640 and rift_s sizes.

    python bench/timewarp.py [--repeats 21] [--threads N]

Warps a random linear RGB frame of each eye by a small head turn (1.5 degrees yaw, 0.5 pitch, about one 80 Hz
frame of a brisk turn) into reused output buffers, as the compositor's display does for a repeat; reports
the median (p50) and the fastest of the repeats for both eyes together, since these machines are shared and
noisy, with the numba thread count (the default config's display warps on one: run.kernel_threads).
"""

from __future__ import annotations

import argparse
import statistics
import time

import numba as nb
import numpy as np

from hmdrt.optics import EyeCamera, get_profile
from hmdrt.present.timewarp import timewarp
from hmdrt.spatial import Pose


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--threads", type=int, default=nb.get_num_threads(), help="numba threads (default: all)")
    args = ap.parse_args()
    nb.set_num_threads(args.threads)

    print(f"timewarp, both eyes, {args.repeats} repeats, {nb.get_num_threads()} numba threads")
    for name in ("sim-cpu-640", "rift_s"):
        profile = get_profile(name)
        eyes = []
        for eye in ("left", "right"):
            rendered = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0]), eye)
            target = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0], 1.5, 0.5), eye)
            image = np.random.default_rng(0).random((profile.height, profile.width, 3), dtype=np.float32)
            eyes.append((image, rendered, target, np.empty_like(image)))
        outside = [timewarp(*eye).outside for eye in eyes]  # warm up numba and threads
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            for eye in eyes:
                timewarp(*eye)
            times.append(time.perf_counter() - t)
        p50, fastest = statistics.median(times) * 1e3, min(times) * 1e3
        print(
            f"  {name:12s} {profile.width}x{profile.height} x 2 eyes  p50 {p50:7.2f} ms  fastest {fastest:7.2f} ms"
            f"  (outside {max(outside):.1%})"
        )


if __name__ == "__main__":
    main()
