"""The compositor's loops. In real time the render loop and the display loop run on their own threads against the
host clock: the render loop wakes when the pacer (hmdrt.compositor.pacer) says, builds the frame and hands it to
the display; the display loop latches a frame at each VSync. In virtual time one loop moves the clock one period per
frame, polls the drivers against it and does both, so that runs reproduce bit for bit. A `stats` thread publishes
the run report each second meanwhile.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numba

from hmdrt.compositor.config import RunConfig
from hmdrt.compositor.pacer import FrameTiming
from hmdrt.compositor.parts import Parts
from hmdrt.errors import ConfigError

MAX_AHEAD = 4  # frames the renderer may hand over before the display has shown them (the pacer remembers 16)
# A thread waiting for the GIL gets it within this (Python's default is 5 ms, a sixth of a 30 Hz frame): the
# display and the hand-over of a finished frame must not wait behind the ingest or a driver for that long.
SWITCH_INTERVAL_S = 0.0005
STATS_S = 1.0  # the `stats` telemetry's interval


SMALL_MACHINE_CORES = 2  # at most this many: "auto" kernel threads are 1 (docs/performance.md, real time)


def kernel_threads(config: RunConfig) -> int:
    """The numba threads of the render and display threads' kernels: run.kernel_threads, 0 for all, "auto" for 1
    on a machine of SMALL_MACHINE_CORES or fewer and all otherwise."""
    wanted, most = config.run.kernel_threads, numba.config.NUMBA_NUM_THREADS
    if wanted == "auto":
        return 1 if (os.cpu_count() or 1) <= SMALL_MACHINE_CORES else most
    if wanted > most:
        raise ConfigError(f"run.kernel_threads = {wanted}: numba has {most} threads (NUMBA_NUM_THREADS)")
    return wanted or most


@contextmanager
def kernels(threads: int) -> Iterator[None]:
    """The calling thread's numba kernels on `threads` threads (numba's setting is per thread)."""
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        yield
    finally:
        numba.set_num_threads(before)


def run(comp: Parts) -> None:
    """The loops until stopped, the frame count or the duration; the compositor is stopped when they return."""
    threading.Thread(target=stats_loop, args=(comp,), name="stats", daemon=True).start()
    switch = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        with kernels(comp.kernel_threads):
            if comp.config.run.virtual_time:
                virtual_loop(comp)
            else:
                display = threading.Thread(target=display_loop, args=(comp,), name="display")
                display.start()
                try:
                    render_loop(comp)
                finally:
                    comp.stop.set()
                    display.join()
    finally:
        sys.setswitchinterval(switch)
        comp.stop.set()


def done(comp: Parts) -> bool:
    """Stopped, or at the run's frame count or duration ([run] frames, duration_s)."""
    if comp.stop.is_set():
        return True
    run = comp.config.run
    if run.frames and comp.report.vsyncs >= run.frames:
        return True
    return bool(run.duration_s) and comp.clock.now_ns() - comp.started_ns >= run.duration_s * 1e9


def render_loop(comp: Parts) -> None:
    clock, display, stop = comp.clock, comp.display, comp.stop
    busy_since = time.perf_counter_ns()  # the loop's own work, outside its waits, counts to the next frame
    while not done(comp):
        if display.backlog >= MAX_AHEAD:  # a stalled display: wait for it rather than run ahead of it
            stop.wait(comp.vsync.period_ns / 1e9)
            busy_since = time.perf_counter_ns()
            continue
        comp.apply_pending()
        with comp.lock:
            timing = comp.pacer.predict(clock.now_ns())
        loop_ns = time.perf_counter_ns() - busy_since
        if stop.wait(max(timing.wake_ns - clock.now_ns(), 0) / 1e9):
            break
        frame = comp.builder.build(timing, clock.now_ns(), loop_ns)
        busy_since = time.perf_counter_ns()
        display.submit(frame)
        with comp.lock:
            comp.pacer.mark_render(timing.frame_id, frame.actual_wake_ns, frame.render_end_ns)


def display_loop(comp: Parts) -> None:
    clock, vsync = comp.clock, comp.vsync
    index = vsync.index_at_or_after(clock.now_ns())
    with kernels(comp.kernel_threads):
        while not done(comp):
            if comp.stop.wait(max(vsync.vsync(index) - clock.now_ns(), 0) / 1e9):
                break
            comp.display.latch(index)
            index += 1
    comp.stop.set()


def virtual_loop(comp: Parts) -> None:
    """One period per frame: the frame's work spans the period before the VSync it is shown at."""
    clock, vsync = comp.clock, comp.vsync
    period, index = vsync.period_ns, 0
    while not done(comp):
        comp.apply_pending()
        t_vsync = vsync.vsync(index)
        clock.advance_to(t_vsync - period)
        comp.sources.poll()
        timing = FrameTiming(
            frame_id=index,
            wake_ns=t_vsync - period,
            desired_present_ns=t_vsync,
            predicted_display_ns=t_vsync + comp.pacer.present_to_display_ns,
            period_ns=period,
            budget_ns=period,
            vsyncs=1,
        )
        frame = comp.builder.build(timing, clock.now_ns())
        comp.display.submit(frame)
        clock.advance_to(t_vsync)
        comp.display.latch(index)
        index += 1


def stats_loop(comp: Parts) -> None:
    while not comp.stop.wait(STATS_S):
        comp.telemetry.publish("stats", comp.summary())
