"""Helpers of the `hmdrt watch` tests: the watch server in this process on a thread of its own, a compositor in
virtual time slowed to the wall clock, and the `hmdrt watch` command in a process of its own."""

from __future__ import annotations

import asyncio
import re
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import zmq

from hmdrt.clock import VirtualClock
from hmdrt.compositor.config import load_config
from hmdrt.testing import Recording
from hmdrt.watch.server import WatchOptions, WatchServer

from .compositor_helpers import readline

URL = re.compile(r"hmdrt watch: (http://\S+/\?token=(\S+)) \(read-only: (http://\S+/)\)")


class WallPacedClock(VirtualClock):
    """Virtual time that never runs ahead of the wall clock: a run reproducible frame for frame that a page can
    watch at the display's rate."""

    def __init__(self) -> None:
        super().__init__(0)
        self._wall0 = time.monotonic_ns()

    def advance_to(self, t_ns: int) -> None:
        ahead = t_ns - (time.monotonic_ns() - self._wall0)
        if ahead > 0:
            time.sleep(ahead / 1e9)
        super().advance_to(t_ns)


class GazeRecording(Recording):
    """The compositor, keeping the eye cameras and gaze directions of each frame it shows, by frame id."""

    def __init__(self, *args, **kwargs):
        self.gazes: dict[int, tuple[dict, dict | None]] = {}
        super().__init__(*args, **kwargs)

    def _shown(self, record, images) -> None:
        self.gazes[record.frame_id] = (self.display.last.cameras, self.display.last.gaze_dirs)
        super()._shown(record, images)


def paced_compositor(config: Path, context: zmq.Context) -> GazeRecording:
    """The compositor of a config in virtual time at the wall clock's pace, for 10 minutes unless stopped."""
    return GazeRecording(
        load_config(config, virtual_time=True, duration_s=600), clock=WallPacedClock(), context=context
    )


def expected_gaze(comp: GazeRecording, header: dict) -> list[list[float]]:
    """Where the compositor's gaze for the preview's frame projects, per eye, in preview pixels."""
    cameras, directions = comp.gazes[header["frame_id"]]
    out = []
    for (eye, camera), placed in zip(cameras.items(), header["eyes"], strict=True):
        gx, gy = camera.gaze_pixel(directions[eye])
        out.append([placed["x0"] + gx * header["scale"], gy * header["scale"]])
    return out


@contextmanager
def watch_server(options: WatchOptions) -> Iterator[WatchServer]:
    """A started WatchServer, served by an event loop on a thread of its own; stopped after."""
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, name="watch-server", daemon=True)
    thread.start()
    server = WatchServer(options)
    try:
        asyncio.run_coroutine_threadsafe(server.start(), loop).result(30)
        yield server
    finally:
        asyncio.run_coroutine_threadsafe(server.stop(), loop).result(30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(10)
        loop.close()


@contextmanager
def watch_process(*args: str) -> Iterator[tuple[subprocess.Popen, str, str, str]]:
    """`hmdrt watch --port 0 ARGS` in a process of its own: (process, URL with the token, token, read-only URL)."""
    process = subprocess.Popen(
        [sys.executable, "-m", "hmdrt", "watch", "--port", "0", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = readline(process, 60)
        match = URL.fullmatch(line.strip())
        assert match, f"hmdrt watch printed {line!r}; stderr: {process.stderr.read() if not line else ''}"
        yield process, *match.groups()
    finally:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()
