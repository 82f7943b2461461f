"""The tracer compiled aside on a first run is the one the compositor then loads: after the second process, the
default config's warm-up finds the tracer's kernel in the cache and compiles it no more (hmdrt.trace.compile_aside);
a process that fails or outlasts its wait leaves the compile to the tracer."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from hmdrt.optics import EyeCamera, get_profile
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace import compile_aside
from hmdrt.trace.integrator import Whitted

LOADS = """
from hmdrt.compositor.config import load_config
from hmdrt.compositor.session import Session
from hmdrt.present.timewarp import _warp
from hmdrt.trace import compile_aside
from hmdrt.trace.wavefront import _trace_blocks

assert compile_aside.cached(), "no index of the tracer in the cache"
session = Session(load_config("configs/default.toml"))
assert session.tracer._aside is None  # a cache that holds the tracer starts no second process
session.warm_up()
session.close()
for kernel in (_trace_blocks, _warp):
    print(sum(kernel.stats.cache_hits.values()), sum(kernel.stats.cache_misses.values()))
"""


ONE_SIGNATURE = """
from hmdrt.api import render_frame
from hmdrt.scene import load_scene
from hmdrt.trace.wavefront import _trace_blocks

for scene in ("whitted", "interior"):
    for method in ("rrm", "kim21", "weier16", "weier18"):
        render_frame(load_scene(scene), "sim-cpu", method, resolution=(32, 36), threads=1)
print(len(_trace_blocks.signatures))
"""


def test_the_tracer_has_one_signature_whatever_the_scene_and_the_method() -> None:
    """What lets the second process compile the tracer on the built-in scene for any config: in a process of its own
    (the suite's may have traced otherwise), four methods on two scenes use one compiled version."""
    run = subprocess.run([sys.executable, "-c", ONE_SIGNATURE], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split()[-1] == "1"


@pytest.mark.slow
def test_the_tracer_compiled_aside_is_loaded_by_the_warm_up_not_compiled(tmp_path) -> None:
    """The tracer, and the timewarp, which the process warps a tiny frame for once it has traced."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    run = subprocess.run([sys.executable, "-c", LOADS], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode != 0 and "no index of the tracer" in run.stderr  # an empty cache is seen as one
    aside = subprocess.run([sys.executable, "-m", compile_aside.__name__], env=env, timeout=600)
    assert aside.returncode == 0
    run = subprocess.run([sys.executable, "-c", LOADS], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    # the tracer and the timewarp: each loaded from the cache once, compiled never
    assert run.stdout.split() == ["1", "0", "1", "0"]


PARTS = """
from hmdrt.scene import load_scene
from hmdrt.trace.integrator import Whitted

with Whitted(load_scene("whitted"), threads=1) as tracer:
    tracer.compile_part(0)
    tracer.compile_part(1)
"""

TRACE = """
import numba.core.event as ev

compiled = []


class Compiles(ev.Listener):
    def on_start(self, event):
        pass

    def on_end(self, event):
        f = event.data["dispatcher"].py_func
        compiled.append(f"{f.__module__}.{f.__qualname__}")


ev.register("numba:compile", Compiles())
from hmdrt.trace import compile_aside

compile_aside.main([])
# the tracer's, not the timewarp's, which the process compiles after it
print(" ".join(sorted({name for name in compiled if name.startswith("hmdrt.") and ".present." not in name})))
"""


@pytest.mark.slow
def test_the_two_parts_are_every_kernel_the_tracer_calls(tmp_path) -> None:
    """Once both parts of the steps' kernels are in the cache, the tracer compiles itself and nothing it calls: the
    parts run the steps with the types the tracer does (a literal argument types as itself, not as an int)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    parts = subprocess.run([sys.executable, "-c", PARTS], env=env, capture_output=True, text=True, timeout=600)
    assert parts.returncode == 0, parts.stderr
    run = subprocess.run([sys.executable, "-c", TRACE], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["hmdrt.kernels.schedule.claim", "hmdrt.trace.wavefront._trace_blocks"]


EMPTY = """
import sys

import numpy as np
from numba.core.registry import CPUDispatcher

from hmdrt.foveation import make_method
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import FrameInput, eye_cameras, frame_requests


def signatures():
    return {
        f"{m}.{k}": len(v.signatures)
        for m, mod in list(sys.modules.items())
        if m.startswith("hmdrt.foveation")
        for k, v in vars(mod).items()
        if isinstance(v, CPUDispatcher) and v.py_func.__module__ == m  # the method's own, not the tracer's helpers
    }


def frames(method, size):
    pose = Pose.looking([0.0, 1.6, 0.0])
    cameras = eye_cameras(get_profile("sim-cpu").with_resolution(*size), pose, ("left", "right"))
    ahead = {"left": np.array([0.0, 0.0, -1.0]), "right": np.array([0.0, 0.0, -1.0])}
    for frame in range(2):
        for request in frame_requests(FrameInput(frame, 0, pose, ahead, None), cameras, 0):
            out = method.render(request, FrameStats())
    return out


with Whitted(load_scene("whitted"), threads=1) as tracer:
    before = signatures()
    with tracer.empty_scene():
        empty = frames(make_method(sys.argv[1], tracer), (32, 36))
    ahead = signatures()
    traced = frames(make_method(sys.argv[1], tracer), (40, 44))
    after = signatures()
print(int(not empty.any()), int(traced.any()))
print(" ".join(sorted(k for k, n in ahead.items() if n > before.get(k, 0))))
print(" ".join(sorted(k for k, n in after.items() if n > ahead.get(k, 0))))
"""


@pytest.mark.parametrize("method", ["rrm", "weier16", "weier18", "kim21"])
def test_frames_of_an_empty_scene_compile_what_a_traced_frame_runs(method) -> None:
    """What lets a start-up compile a method while the tracer compiles aside (Session.warm_up): in a process of its
    own, two frames against an empty scene (black misses, traced by nothing) compile the method's kernels, and two
    traced frames of another size then compile none of them again."""
    run = subprocess.run([sys.executable, "-c", EMPTY, method], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    images, ahead, again = run.stdout.split("\n")[:3]
    assert images.split() == ["1", "1"]  # the empty scene's frames are black, the whitted scene's are not
    assert ahead.split(), "the empty scene's frames compiled nothing"
    assert again.split() == []


TWICE = """
import sys
from collections import defaultdict

import numba.core.event as ev
import numpy as np

compiled = defaultdict(set)  # each function compiled here, with the argument types of each of its compiles


class Compiles(ev.Listener):
    def on_start(self, event):
        pass

    def on_end(self, event):
        f = event.data["dispatcher"].py_func
        compiled[f"{f.__module__}.{f.__qualname__}"].add(tuple(str(a) for a in event.data["args"]))


ev.register("numba:compile", Compiles())
from hmdrt.foveation import make_method
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import FrameInput, eye_cameras, frame_requests

pose = Pose.looking([0.0, 1.6, 0.0])
cameras = eye_cameras(get_profile("sim-cpu").with_resolution(32, 36), pose, ("left", "right"))
ahead = {"left": np.array([0.0, 0.0, -1.0]), "right": np.array([0.0, 0.0, -1.0])}
with Whitted(load_scene("whitted"), threads=2) as tracer, tracer.empty_scene():
    method = make_method(sys.argv[1], tracer)
    for frame in range(2):
        for request in frame_requests(FrameInput(frame, 0, pose, ahead, None), cameras, 0):
            method.render(request, FrameStats())
print(" ".join(sorted(
    name for name, versions in compiled.items()
    if name.startswith("hmdrt.")
    and len({tuple("int64" if a == "uint64" else a for a in args) for args in versions}) < len(versions)
)))
"""


@pytest.mark.slow
@pytest.mark.parametrize("method", ["rrm", "weier16", "weier18", "kim21"])
def test_no_helper_compiles_for_a_signed_and_an_unsigned_index(method, tmp_path) -> None:
    """A prange's index is uint64 in the loop numba runs and int64 where numba first types the kernel, so a helper
    given it as it is compiles twice, once for nothing (hmdrt/kernels/jit.py): from an empty cache, a method's
    kernels (compiled against the empty scene) compile no function for both."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    run = subprocess.run([sys.executable, "-c", TWICE, method], env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == []


def test_a_part_then_the_tracer_once_the_caller_releases_the_process() -> None:
    """--part compiles (here: loads) its part, then waits for its input to close before it traces."""
    command = [sys.executable, "-m", compile_aside.__name__, "--part", "0"]
    process = subprocess.Popen(command, stdin=subprocess.PIPE)
    with pytest.raises(subprocess.TimeoutExpired):
        process.wait(8)  # waiting for the caller's part (with a warm cache it would have traced by now)
    compile_aside.release(process)
    assert process.wait(120) == 0


def test_no_process_when_the_cache_holds_the_tracer() -> None:
    compile_aside.main([])  # compiled in this process, or loaded from its cache
    assert compile_aside.cached()
    assert compile_aside.start() is None
    with Whitted(load_scene("whitted"), threads=1, aside=True) as tracer:
        assert tracer._aside is None


def tiny_trace(tracer: Whitted) -> None:
    camera = EyeCamera.for_eye(get_profile("sim-cpu").with_resolution(4, 4), Pose.looking([0.0, 1.6, 0.0]))
    xy = [[x + 0.5, 2.5] for x in range(4)]
    out = tracer.trace_samples(camera, np.array(xy, np.float32), np.arange(4, dtype=np.int64), FrameStats())
    assert out.shape == (4, 3) and np.isfinite(out).all()


def test_a_second_process_that_fails_leaves_the_tracer_to_trace(caplog) -> None:
    with Whitted(load_scene("whitted"), threads=1) as tracer:
        tracer._aside = subprocess.Popen([sys.executable, "-c", "raise SystemExit(3)"])
        with caplog.at_level("INFO", logger=compile_aside.__name__):
            tiny_trace(tracer)
        assert tracer._aside is None
    assert "exited 3; compiling it here" in caplog.text


def test_a_second_process_past_its_wait_is_stopped() -> None:
    process = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    start = time.monotonic()
    compile_aside.finish(process, timeout_s=0.2)
    assert process.returncode is not None and time.monotonic() - start < 30


def test_closing_a_tracer_stops_its_second_process() -> None:
    tracer = Whitted(load_scene("whitted"), threads=1)
    process = tracer._aside = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    tracer.close()
    assert process.returncode is not None and tracer._aside is None
