"""The tracer compiled into numba's cache by a second process on a first run, while the start-up that asked for it
compiles everything else (the method's own kernels, the timewarp, a driver's clock fit) on the other core: the
tracer is 21 s of the 27 s that a first run of the default config compiles (docs/performance.md, "The first run").
Then the process warps a tiny frame, so that a start-up still compiling a method's kernels (kim21's take longer than
the tracer) finds the timewarp in the cache, where a start-up that has come to it first compiles it itself.

    python -m hmdrt.trace.compile_aside [--part 0]

The kernels that the tracer's steps call take half of it, and they come in two parts (wavefront.compile_part): with
--part, the process compiles that part, then waits for its standard input to close, which the caller does once it
has compiled the other part itself (release), and compiles the tracer around both.

The tracer's kernel has one signature whatever the scene and the method (Frame always carries a G-buffer and a
light buffer, empty where none is asked for), so tracing a few samples of the built-in `whitted` scene compiles
what every run traces with. A tracer that asked for the process (Whitted(..., aside=True)) waits for it before its
first trace and then loads the kernel from the cache. A warm cache, or a machine without a second CPU for this
process, starts none; a process that fails or outlasts WAIT_S leaves the compile to the tracer, as without it.
"""

from __future__ import annotations

import argparse
import logging
import os
import subprocess
import sys

log = logging.getLogger(__name__)

WAIT_S = 180.0  # the longest a first trace waits for the process (it compiles in about 25 s on these 2 cores)
PART = 0  # the part of the steps' kernels (wavefront.compile_part) the process compiles; the caller compiles the other


def cached() -> bool:
    """Whether numba's cache holds an index of the tracer's kernel (its compiled versions are listed there). The
    index's path is numba's own, not public: a numba that keeps it elsewhere counts as cached (no second process)."""
    from hmdrt.trace.wavefront import _trace_blocks

    try:
        index = _trace_blocks._cache._cache_file._index_path
    except AttributeError:
        return True
    return os.path.exists(index)


def start() -> subprocess.Popen | None:
    """The process compiling the tracer, or None when the cache holds it, only one CPU is ours, or no process could
    start."""
    if len(os.sched_getaffinity(0)) < 2 or cached():
        return None
    try:
        return subprocess.Popen(
            [sys.executable, "-m", __name__, "--part", str(PART)],
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    except OSError as exc:
        log.debug("compiling the tracer in this process instead: %s", exc)
        return None


def release(process: subprocess.Popen) -> None:
    """Lets `process` go on from its part to the tracer: the caller's part is in the cache, or never will be."""
    if process.stdin is not None and not process.stdin.closed:
        process.stdin.close()


def finish(process: subprocess.Popen, timeout_s: float = WAIT_S) -> None:
    """Waits for `process` to put the tracer in the cache; one that has not ended within timeout_s is stopped, and
    the caller compiles the tracer itself (as it does when the process failed)."""
    release(process)
    try:
        code = process.wait(timeout_s)
    except subprocess.TimeoutExpired:
        code = None
        stop(process)
    if code != 0:
        log.info("the tracer's second process %s; compiling it here", "timed out" if code is None else f"exited {code}")


def stop(process: subprocess.Popen) -> None:
    """Ends `process` where it still runs."""
    if process.poll() is None:
        process.kill()
    process.wait()
    release(process)


def main(argv: list[str] | None = None) -> None:
    """Trace a few samples of the built-in `whitted` scene on one thread: the kernel's types depend on neither. With
    --part, that part of the steps' kernels first, then the tracer once standard input has closed."""
    ap = argparse.ArgumentParser(prog=f"python -m {__name__}", description=__doc__.splitlines()[0])
    ap.add_argument("--part", type=int, choices=range(2), help="compile this part first, then wait for stdin to close")
    args = ap.parse_args(argv)
    import numpy as np

    from hmdrt.optics import EyeCamera, get_profile
    from hmdrt.present.timewarp import timewarp
    from hmdrt.scene import load_scene
    from hmdrt.spatial import Pose
    from hmdrt.telemetry.stats import FrameStats
    from hmdrt.trace.integrator import Whitted

    profile = get_profile("sim-cpu").with_resolution(8, 8)
    camera = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0]), "left")
    xy = np.stack(np.meshgrid(np.arange(8) + 0.5, np.arange(8) + 0.5), -1).reshape(-1, 2).astype(np.float32)
    with Whitted(load_scene("whitted"), threads=1) as tracer:
        if args.part is not None:
            tracer.compile_part(args.part)
            sys.stdin.read()  # until the caller has its part in the cache (release)
        tracer.trace_samples(camera, xy, np.arange(len(xy), dtype=np.int64), FrameStats())
    timewarp(np.zeros((8, 8, 3), np.float32), camera, camera)  # for a start-up still compiling its method


if __name__ == "__main__":
    main()
