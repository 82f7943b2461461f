"""Milliseconds per eye of rotational timewarp (hmdrt.present.timewarp) at sim-cpu and rift_s sizes.

    python bench/timewarp.py [--repeats 21]

Warps a random linear RGB frame of one left eye by a small head turn (1.5 degrees yaw, 0.5 pitch,
about one 80 Hz frame of a brisk turn) into a reused output buffer; reports the median of the repeats,
since these machines are shared and noisy, with numba's thread count.
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
    args = ap.parse_args()

    print(f"timewarp, one eye, median of {args.repeats}, {nb.get_num_threads()} numba threads")
    for name in ("sim-cpu", "rift_s"):
        profile = get_profile(name)
        rendered = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0]))
        target = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0], 1.5, 0.5))
        image = np.random.default_rng(0).random((profile.height, profile.width, 3), dtype=np.float32)
        out = np.empty_like(image)
        outside = timewarp(image, rendered, target, out).outside  # warm up numba and threads
        times = []
        for _ in range(args.repeats):
            t = time.perf_counter()
            timewarp(image, rendered, target, out)
            times.append(time.perf_counter() - t)
        ms = statistics.median(times) * 1e3
        print(f"  {name:8s} {profile.width}x{profile.height}  {ms:7.2f} ms/eye  (outside {outside:.1%})")


if __name__ == "__main__":
    main()
