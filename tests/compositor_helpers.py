"""What the compositor tests share: the run report's keys, image digests, telemetry subscriptions, the command
line in a subprocess and its one-line errors."""

from __future__ import annotations

import hashlib
import selectors
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zmq

from hmdrt.compositor.daemon import Compositor

# report fields measured on the wall clock, which differ between runs also in virtual time
WALL_CLOCK = ("frame_ms", "compositor_overhead_ms", "timewarp_ms", "stages_ms")
REPORT_KEYS = {
    "frames",
    "vsyncs",
    "vsync_hz",
    "presented",
    "re_presented",
    "repeat_rate",
    "late",
    "dropped",
    "out_of_order",
    "deadline_misses",
    "miss_rate",
    "frame_ms",
    "latency_ms",
    "gaze_error_at_photon_deg",
    "stages_ms",
    "rays_per_frame",
    "method",
    "profile",
    "display",
    "drivers",
    "pacing",
    "image_buffers",
}
PERCENTILES = {"p50", "p95", "p99", "max"}


def digest(images: list[np.ndarray]) -> str:
    return hashlib.sha256(b"".join(np.ascontiguousarray(i).tobytes() for i in images)).hexdigest()


def subscribe(context: zmq.Context, comp: Compositor) -> zmq.Socket:
    """A SUB socket on the compositor's telemetry, known to be connected: a probe went through."""
    sub = context.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(comp.telemetry.address)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        comp.telemetry.publish("probe", {})
        if sub.poll(50):
            return sub
    pytest.fail("the telemetry subscription never connected")


def receive(sub: zmq.Socket, topic: bytes, count: int, timeout_s: float = 10.0) -> list[dict]:
    """Up to `count` messages of `topic`, decoded; what arrived by timeout_s."""
    out, deadline = [], time.monotonic() + timeout_s
    while len(out) < count and time.monotonic() < deadline:
        if sub.poll(100):
            frames = sub.recv_multipart()
            if frames[0] == topic:
                out.append(msgspec.msgpack.decode(frames[1]))
    return out


def hmdrt(*args: str, timeout_s: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hmdrt", *args], capture_output=True, text=True, timeout=timeout_s)


def assert_one_line_error(stderr: str, message: str) -> None:
    lines = stderr.strip().splitlines()
    assert "Traceback" not in stderr and len(lines) == 1, stderr
    assert lines[0].startswith("hmdrt: error: ") and message in lines[0], stderr


def readline(process: subprocess.Popen, timeout_s: float) -> str:
    with selectors.DefaultSelector() as sel:
        sel.register(process.stdout, selectors.EVENT_READ)
        if not sel.select(timeout_s):
            pytest.fail(f"no output from {process.args} within {timeout_s} s")
    return process.stdout.readline()


def start_run(config: Path, report: Path) -> subprocess.Popen:
    """`hmdrt run CONFIG --report REPORT` in its own process, its output piped as text."""
    return subprocess.Popen(
        [sys.executable, "-m", "hmdrt", "run", str(config), "--report", str(report)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
