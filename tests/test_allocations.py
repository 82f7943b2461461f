"""No per-frame allocation of image-sized arrays in steady state.

Every method renders frames 0-2 of the built-in head path at 256x288 (its buffers grow to their working
size there), then frames 3-10 into a caller's buffer under tracemalloc, which sees numpy's and Python's
allocations. The peak memory a frame reaches above what was live before it must stay under LIMIT, below
the smallest per-pixel array of that size (a 256x288 bool mask is 72 KB), so a temporary mask, map or
sample array allocated anywhere in the frame (method, tracer, stages) fails the test. A frame's Python
bookkeeping (arguments unboxed for the kernels, stage timings) peaks at 13-17 KB.
"""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from hmdrt.foveation import make_method
from hmdrt.foveation.registry import allocation_cases
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import builtin_path, eye_cameras, frame_requests

LIMIT = 48 * 1024  # bytes of peak growth per frame: Python bookkeeping (the tracer pool's futures: kim21 traces
# several times a frame), no array of the image's size (884 KB at SIZE)
SIZE = (256, 288)


def frame_peaks(scene: str, spec: str, frames: range = range(3, 11)) -> list[int]:
    """Per frame in `frames`: the peak traced memory during its render above what was live before it."""
    profile = get_profile("sim-cpu").with_resolution(*SIZE)
    loaded = load_scene(scene)
    inputs = builtin_path(frames.stop, profile.period_ns, loaded.start)
    out = np.empty((profile.height, profile.width, 3), np.float32)
    peaks = []
    with Whitted(loaded) as tracer:
        method = make_method(spec, tracer)
        for inp in inputs:
            (request,) = frame_requests(inp, eye_cameras(profile, inp.pose, ("left",)), 0)
            stats = FrameStats()
            traced = inp.frame in frames
            if traced:
                tracemalloc.start()
                before = tracemalloc.get_traced_memory()[0]
            image = method.render(request, stats, out)
            if traced:
                peaks.append(tracemalloc.get_traced_memory()[1] - before)
                tracemalloc.stop()
            assert image is out
    return peaks


CASES = allocation_cases()  # the registered methods' golden cases (base.Checks.golden)


@pytest.mark.parametrize(("scene", "spec"), CASES)
def test_steady_state_frames_allocate_nothing_image_sized(scene: str, spec: str) -> None:
    peaks = frame_peaks(scene, spec)
    assert max(peaks) <= LIMIT, f"{spec} on {scene}: per-frame peak allocations {peaks} bytes"


def test_allocation_check_sees_a_temporary_mask() -> None:
    """The measurement itself: a frame that allocates one 256x288 bool mask shows it."""
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    mask = np.zeros(SIZE[::-1], bool)
    del mask
    peak = tracemalloc.get_traced_memory()[1] - before
    tracemalloc.stop()
    assert peak > LIMIT
