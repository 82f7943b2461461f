"""The timewarp compiled aside on a first run is the one the compositor then loads: a process warping a frame of
the default display's size finds it in the cache, compiling nothing (hmdrt.present.compile_aside)."""

from __future__ import annotations

import os
import subprocess
import sys

from hmdrt.present import compile_aside

LOADS = """
import numpy as np
from hmdrt.compositor.config import load_config
from hmdrt.compositor.session import display_profile
from hmdrt.optics import EyeCamera
from hmdrt.present import compile_aside
from hmdrt.present.timewarp import _warp, timewarp
from hmdrt.spatial import Pose

assert compile_aside.cached(), "no index of the timewarp in the cache"
profile = display_profile(load_config("configs/default.toml"))
camera = EyeCamera.for_eye(profile, Pose.looking([0.0, 1.6, 0.0]), "right")
timewarp(np.ones((profile.height, profile.width, 3), np.float32), camera, camera)
print(sum(_warp.stats.cache_hits.values()), sum(_warp.stats.cache_misses.values()))
"""


def test_the_timewarp_compiled_aside_is_loaded_not_compiled(tmp_path) -> None:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    run = subprocess.run([sys.executable, "-c", LOADS], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode != 0 and "no index of the timewarp" in run.stderr  # an empty cache is seen as one
    aside = subprocess.run([sys.executable, "-m", compile_aside.__name__], env=env, timeout=300)
    assert aside.returncode == 0
    run = subprocess.run([sys.executable, "-c", LOADS], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["1", "0"]  # one load from the cache, no compile


def test_no_process_when_the_cache_holds_the_timewarp() -> None:
    compile_aside.main()  # compiled in this process, or loaded from its cache
    assert compile_aside.cached()
    assert compile_aside.start() is None
