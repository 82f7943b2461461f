"""Test helpers: small renders of real scenes through the real tracer, virtual clocks, and reading drivers
until something holds."""

from __future__ import annotations

import json
import socket
import subprocess
import threading
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import msgspec
import numpy as np
import pytest
from numpy.typing import ArrayLike

from hmdrt.api import render_frame
from hmdrt.bus.messages import Gaze
from hmdrt.cli import main
from hmdrt.clock import VirtualClock
from hmdrt.drivers.base import DeviceLost, Driver, Sample
from hmdrt.drivers.emulators.base import Emulator
from hmdrt.drivers.protocols import fove
from hmdrt.foveation import MethodChoice
from hmdrt.optics import get_profile
from hmdrt.replay.trace import write_trace
from hmdrt.scene import Scene
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats

DATA = Path(__file__).parent / "data"
FORWARD = np.array([0.0, 0.0, -1.0])


def reap(process: subprocess.Popen) -> None:
    """At a test's end: kill a child process that still runs (the test failed before it ended) and wait for it."""
    if process.poll() is None:
        process.kill()
        process.communicate()


def render(
    scene: Scene | str,
    width: int = 64,
    height: int = 72,
    method: str = "full",
    pose: Pose | None = None,
    seed: int = 0,
    ipd_mm: float | None = None,
    **options,
) -> tuple[np.ndarray, FrameStats]:
    """One frame of a scene through sim-cpu optics at a small resolution, gaze ahead (hmdrt.api.render_frame)."""
    profile = get_profile("sim-cpu")
    if ipd_mm is not None:
        profile = msgspec.structs.replace(profile, ipd_mm=ipd_mm)
    choice = MethodChoice.parse(method, **options)
    frame = render_frame(
        scene, profile, choice, FORWARD, resolution=(width, height), pose=pose, seed=seed, gbuffer=False
    )
    return frame.image, frame.stats


class SteppingClock(VirtualClock):
    """A virtual clock whose sleeps return at once with the time moved on: a stub runs faster than real time."""

    def sleep_until(self, t_ns: int) -> None:
        self.advance_to(max(self.now_ns(), t_ns))


def wait_for(condition: Callable[[], bool], timeout_s: float = 10.0) -> bool:
    """Poll condition() until it holds or timeout_s passes; whether it holds."""
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.005)
    return condition()


def at_least(n: int) -> Callable[[list], bool]:
    """A `collect` condition: n samples or more."""
    return lambda samples: len(samples) >= n


def collect(driver: Driver, until: Callable[[list], bool] | None = None, timeout_s: float = 5.0) -> list[Sample]:
    """Read from driver until `until(samples)` holds or timeout_s passes (None: read for all of timeout_s)."""
    samples: list[Sample] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and not (until is not None and until(samples)):
        samples += driver.read(0.05)
    return samples


def assert_lost_when_stopped(emulator: Emulator, driver: Driver, match: str | None = None) -> None:
    """Open driver on the running emulator and see samples; once the emulator stops, reads raise DeviceLost."""
    driver.open()
    assert collect(driver, at_least(3))
    emulator.stop()
    with pytest.raises(DeviceLost, match=match):
        collect(driver, timeout_s=10.0)


def gaze_trace(
    path: Path, eyes: Iterable[tuple[ArrayLike, ArrayLike, bool]], period_ns: int, depth_m: float | None = None
) -> str:
    """Write a binocular gaze trace, sample k at k * period_ns with eyes[k] = (left, right, valid); its path."""
    samples = [
        Gaze(seq=k, t_host=k * period_ns, valid=valid, L=tuple(left), R=tuple(right), depth_m=depth_m)
        for k, (left, right, valid) in enumerate(eyes)
    ]
    write_trace(path, samples, device="test")
    return str(path)


# docs/protocols.md, Test vectors (Pupil): a binocular gaze datum
SECTION7_GAZE = {
    "topic": "gaze.3d.01.",
    "confidence": 0.97,
    "norm_pos": [0.5, 0.5],
    "timestamp": 535741.7153,
    "gaze_point_3d": [0.0, 0.0, 500.0],
    "gaze_normals_3d": {"0": [0.06, 0.0, 0.998], "1": [-0.06, 0.0, 0.998]},
    "eye_centers_3d": {"0": [-30.0, 0.0, -20.0], "1": [30.0, 0.0, -20.0]},
    "base_data": [],
}


class ScriptedFoveServer:
    """A FOVE server written with the codec over a real socket: hello, wait for subscribe, send `script`."""

    def __init__(self, script: list[bytes]):
        self.script = script
        self.subscribe: fove.Record | None = None
        self._listener = socket.create_server(("127.0.0.1", 0))
        self.url = f"fove://127.0.0.1:{self._listener.getsockname()[1]}?timeout=5"
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)

    def _serve(self) -> None:
        conn, _ = self._listener.accept()
        with conn:
            conn.settimeout(5.0)
            conn.sendall(fove.encode(fove.Hello(fove.API_VERSION, int(fove.Capability(0b11011)))))
            reader, payloads = fove.FrameReader(), []
            while not payloads:
                payloads = reader.feed(conn.recv(4096))
            self.subscribe = fove.decode(payloads[0])
            for chunk in self.script:
                conn.sendall(chunk)
            self._done.wait(10.0)

    def __enter__(self) -> ScriptedFoveServer:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._done.set()
        self._thread.join(5.0)
        self._listener.close()


def eval_results(folder: Path, name: str, config_text: str) -> dict:
    """results.json of `hmdrt eval` on config_text, written as folder/NAME.toml and run into folder/NAME."""
    config = folder / f"{name}.toml"
    config.write_text(config_text)
    assert main(["eval", str(config), "--out", str(folder / name), "--no-plots"]) == 0
    return json.loads((folder / name / "results.json").read_text())
