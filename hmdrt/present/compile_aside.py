"""The timewarp compiled into numba's cache by a second process while the compositor's start-up compiles the
method and the tracer, on a first run: the tracer takes one core for about 20 s there, and the timewarp's 2 s of
compiling would otherwise follow it on the same core (docs/performance.md, "The first run").

    python -m hmdrt.present.compile_aside

A run whose cache already holds the timewarp starts no process. Where the second process is slower than the start-up
(no free core), the start-up compiles the timewarp itself, as it would without it, and stops the process.
"""

from __future__ import annotations

import logging
import os
import subprocess
import sys

log = logging.getLogger(__name__)


def cached() -> bool:
    """Whether numba's cache holds an index of the timewarp's kernel (its compiled versions are listed there). The
    index's path is numba's own, not public: a numba that keeps it elsewhere counts as cached (no second process)."""
    from hmdrt.present.timewarp import _warp

    try:
        index = _warp._cache._cache_file._index_path
    except AttributeError:
        return True
    return os.path.exists(index)


def start() -> subprocess.Popen | None:
    """The process compiling the timewarp, or None when the cache holds it or no process could start."""
    if cached():
        return None
    try:
        return subprocess.Popen(
            [sys.executable, "-m", __name__],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
    except OSError as exc:
        log.debug("compiling the timewarp in the start-up instead: %s", exc)
        return None


def stop(process: subprocess.Popen | None) -> None:
    """Ends `process` once the start-up has compiled what it needs: its work is then either in the cache or done
    twice."""
    if process is None:
        return
    if process.poll() is None:
        process.kill()
    process.wait()


def main() -> None:
    """Warp a tiny frame: the kernel's types do not depend on the size, so this compiles what the compositor runs."""
    import numpy as np

    from hmdrt.optics import EyeCamera, get_profile
    from hmdrt.present.timewarp import timewarp
    from hmdrt.spatial import Pose

    profile = get_profile("sim-cpu").with_resolution(8, 8)
    camera = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0]), "left")
    timewarp(np.zeros((8, 8, 3), np.float32), camera, camera)


if __name__ == "__main__":
    main()
