"""The live view yields the cores to the compositor's threads: the preview thread and the `hmdrt watch` process run
at a nice value BACKGROUND_NICE above the compositor's (hmdrt.priority)."""

from __future__ import annotations

import os
import time
import types

from hmdrt.compositor.preview import PreviewPublisher
from hmdrt.priority import BACKGROUND_NICE, MOST_NICE
from tests.watching import watch_process


def nice_of(tid: int) -> int:
    return os.getpriority(os.PRIO_PROCESS, tid)


def expected() -> int:
    return min(nice_of(0) + BACKGROUND_NICE, MOST_NICE)


def test_the_preview_thread_runs_below_the_compositors_threads() -> None:
    publisher = PreviewPublisher(types.SimpleNamespace())  # its worker only: no frame is offered
    try:
        deadline = time.monotonic() + 10
        while nice_of(publisher._thread.native_id) != expected() and time.monotonic() < deadline:
            time.sleep(0.01)
        assert nice_of(publisher._thread.native_id) == expected()
        assert nice_of(0) < expected() or nice_of(0) == MOST_NICE  # the caller's own priority is untouched
    finally:
        publisher.close()


def test_hmdrt_watch_runs_below_the_compositor(tmp_path) -> None:
    endpoints = ("--control", f"ipc://{tmp_path}/control.sock", "--telemetry", f"ipc://{tmp_path}/telemetry.sock")
    with watch_process(*endpoints) as (process, *_):
        threads = os.listdir(f"/proc/{process.pid}/task")
        assert {nice_of(int(tid)) for tid in threads} == {expected()}  # the server's threads inherit it
