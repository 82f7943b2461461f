"""Milliseconds of rotational timewarp (hmdrt.present.timewarp) for both eyes at sim-cpu-640 and rift_s sizes.

    python bench/timewarp.py [--repeats 21] [--threads N] [--against REV]

Warps a random linear RGB frame of each eye by a small head turn (1.5 degrees yaw, 0.5 pitch, about one 80 Hz
frame of a brisk turn) into reused output buffers, as the compositor's display does for a repeat; reports
the median (p50) and the fastest of the repeats for both eyes together, with the numba thread count (the
default config's display warps on one: run.kernel_threads) and the CPU. Each repeat also times, right after
the warp, a numba copy of the same bytes (both eyes' images read, both outputs written, on as many threads): the
floor of any pass over them. With --against, the warp as it was at git revision REV (hmdrt/present/timewarp.py
there, loaded beside this one) is timed in the same repeats too. These machines are shared and noisy, so each
ratio printed is the median of the repeats' own ratios, every variant timed within a few milliseconds of the
others.
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numba as nb
import numpy as np
from llvmlite import binding
from references import copy_rows, module_at

from hmdrt.evaluate.provenance import machine
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.present import timewarp
from hmdrt.spatial import Pose


def simd() -> str:
    """The vector extensions numba compiles for here, of those that decide this kernel's instructions."""
    features = binding.get_host_cpu_features()
    return " ".join(name for name in ("avx2", "fma", "avx512f") if features.get(name)) or "none of avx2, fma, avx512f"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--threads", type=int, default=nb.get_num_threads(), help="numba threads (default: all)")
    ap.add_argument("--against", metavar="REV", help="also time the warp at this git revision, in the same repeats")
    args = ap.parse_args()
    nb.set_num_threads(args.threads)

    print(f"timewarp, both eyes, {args.repeats} repeats, {nb.get_num_threads()} numba threads")
    print(f"  {machine()}; {simd()}")
    with tempfile.TemporaryDirectory() as folder:
        warps: dict[str, Callable] = {"warp": timewarp.timewarp}
        if args.against:
            warps[args.against] = module_at(args.against, "hmdrt/present/timewarp.py", Path(folder)).timewarp
        for name in ("sim-cpu-640", "rift_s"):
            profile = get_profile(name)
            eyes = []
            for eye in ("left", "right"):
                rendered = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0]), eye)
                target = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0], 1.5, 0.5), eye)
                image = np.random.default_rng(0).random((profile.height, profile.width, 3), dtype=np.float32)
                eyes.append((image, rendered, target, np.empty_like(image)))
            flat = [(image.reshape(profile.height, -1), out.reshape(profile.height, -1)) for image, _, _, out in eyes]

            def copy(_: Callable, flat: list = flat) -> None:
                for src, dst in flat:
                    copy_rows(src, dst)

            def warp(warp: Callable, eyes: list = eyes) -> None:
                for eye in eyes:
                    warp(*eye)

            variants = {label: (warp, w) for label, w in warps.items()} | {"copy": (copy, None)}
            outside = [timewarp.timewarp(*eye).outside for eye in eyes]
            for run, arg in variants.values():  # warm up numba and threads
                run(arg)
            times: dict[str, list[float]] = {label: [] for label in variants}
            for _ in range(args.repeats):
                for label, (run, arg) in variants.items():
                    t = time.perf_counter()
                    run(arg)
                    times[label].append(time.perf_counter() - t)
            print(f"  {name} {profile.width}x{profile.height} x 2 eyes (outside {max(outside):.1%}):")
            for label, ts in times.items():
                over_copy = statistics.median(t / c for t, c in zip(ts, times["copy"], strict=True))
                line = f"    {label:12s} p50 {statistics.median(ts) * 1e3:7.2f} ms  fastest {min(ts) * 1e3:7.2f} ms"
                line += f"  {over_copy:5.2f}x the copy"
                if args.against and label == "warp":
                    before = statistics.median(b / t for t, b in zip(ts, times[args.against], strict=True))
                    line += f"  {before:5.2f}x faster than {args.against}"
                print(line)


if __name__ == "__main__":
    main()
