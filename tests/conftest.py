"""Shared fixtures, after pyzmq's test base: a fresh ZeroMQ context per test whose sockets are tracked and closed
with linger 0, and a per-test time limit so that a hung socket fails its test rather than hanging the run. The
context, the runtime folder and the compositors come from hmdrt's pytest plugin (hmdrt.testing.pytest_plugin)."""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zmq

from hmdrt.api import render_frame
from hmdrt.foveation import METHODS
from hmdrt.scene import Scene, load_scene

log = logging.getLogger(__name__)

TEST_TIMEOUT_S = 300  # the slowest default test takes ~15 s on a cold cache; the soak (-m slow) ~100 s


def pytest_sessionstart(session: pytest.Session) -> None:
    """Compile (or load from numba's cache) every method's kernels before the first test, in each process that runs
    tests, so that --durations blames each test for its own time and not for the compiles it happened to do first
    (on a cold cache about 3 minutes, 1-2 s warm)."""
    if getattr(session.config.option, "numprocesses", None) and not hasattr(session.config, "workerinput"):
        return  # the xdist controller runs no tests
    started = time.perf_counter()
    scene = load_scene("whitted")
    for name in METHODS:
        render_frame(scene, "sim-cpu", name, resolution=(32, 36), threads=1)
    log.info("kernels ready in %.1f s", time.perf_counter() - started)


@pytest.fixture(scope="session")
def whitted_scene() -> Scene:
    return load_scene("whitted")


@pytest.fixture
def context(hmdrt_context: zmq.Context) -> zmq.Context:
    """A ZeroMQ context of this test's own (each has room for its own ZAP handler), destroyed with linger 0."""
    return hmdrt_context


@pytest.fixture(autouse=True)
def runtime_dir(hmdrt_runtime_dir: Path) -> Path:
    """Every test gets an XDG_RUNTIME_DIR of its own (the plugin's hmdrt_runtime_dir), also for its subprocesses."""
    return hmdrt_runtime_dir


@pytest.fixture
def own_signals() -> Iterator[None]:
    """`hmdrt run` in this process installs its SIGINT, SIGTERM and SIGHUP handlers: put pytest's back after."""
    saved = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    yield
    for sig, handler in saved.items():
        signal.signal(sig, handler)


@pytest.fixture
def sockets(context: zmq.Context) -> Callable[[int], zmq.Socket]:
    """sockets(kind): a socket on the test's context with linger 0, closed when the test ends."""

    def make(kind: int) -> zmq.Socket:
        sock = context.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        return sock

    return make


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_call(item: pytest.Item):
    """Fail a test that runs longer than TEST_TIMEOUT_S (SIGALRM in the main thread, where pytest runs tests)."""
    if not hasattr(signal, "SIGALRM"):
        yield
        return

    def expired(signum, frame):
        pytest.fail(f"{item.nodeid} ran longer than {TEST_TIMEOUT_S} s", pytrace=False)

    previous = signal.signal(signal.SIGALRM, expired)
    signal.alarm(TEST_TIMEOUT_S)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
