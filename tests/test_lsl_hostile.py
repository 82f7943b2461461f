"""Streams that lie, and drivers that fail: real pylsl outlets whose meta-data lies (a string format, 1,025 channels,
36 channels described on a 5-channel stream) read by the compositor's driver threads, and a driver failing in each of
its calls. Each failure is a counted crash, restarted with backoff, logged in one line (the traceback only at debug
level); no driver thread dies and no traceback reaches stderr.

LSL's discovery is kept to this machine as in tests/test_lsl.py (its `lsl` fixture); every stream has a source_id of
its own.
"""

from __future__ import annotations

import logging
import threading
import uuid

import msgspec
import pytest
import zmq

from hmdrt.bus.messages import decode
from hmdrt.clock import MONOTONIC, VirtualClock
from hmdrt.compositor.sources import Sources
from hmdrt.drivers import REGISTRY, register
from hmdrt.drivers.base import Sample
from hmdrt.drivers.emulators.lsl_source import titta_channels
from hmdrt.drivers.lsl import _checked_meta
from hmdrt.drivers.protocols.lsl_gaze import MetadataError
from hmdrt.drivers.synthetic import SyntheticDriver
from hmdrt.testing import compositor, run_bounded, write_config

from .helpers import wait_for
from .test_lsl import lsl as lsl  # noqa: F401 - its module fixture: LSL's discovery on this machine only

LIES = {  # lie: (channel format, channel count, channels described), what the one log line says is wrong
    "string": (("string", 5, 5), "has channel format 'string'; gaze needs numbers"),
    "1025 channels": (("double64", 1025, 5), "gives channel_count '1025', not a number within 1-1024"),
    "36 described on 5": (("double64", 5, 36), "describes 36 channels of a stream of 5"),
}
RECONNECT_LOG = "hmdrt.drivers.reconnect"


def lying_outlet(lsl, lie: str):
    """A real outlet of type Gaze whose meta-data tells the lie; the outlet and the lsl:// URL of it (name= is the
    stream's name and the bus device)."""
    (channel_format, count, described), _ = LIES[lie]
    name = f"lie-{lie.replace(' ', '-')}-{uuid.uuid4().hex[:8]}"
    info = lsl.StreamInfo(name, "Gaze", count, 100.0, channel_format, f"hmdrt-test-{uuid.uuid4().hex[:12]}")
    channels = info.desc().append_child("channels")
    for label, eye, kind, unit in (titta_channels() * 2)[:described]:
        channel = channels.append_child("channel")
        for key, value in (("label", label), ("eye", eye), ("type", kind), ("unit", unit)):
            channel.append_child_value(key, value)
    return lsl.StreamOutlet(info), f"lsl://?name={name}&source_id={info.source_id()}&timeout=2", name


def states(socket: zmq.Socket) -> list[str]:
    """The states of the status messages waiting on a SUB socket (read while the driver runs: a SUB drops what
    a publisher that went away left unread)."""
    got = []
    while socket.poll(0):
        got.append(decode(socket.recv_multipart())[2].state)
    return got


def crash_lines(records: list[logging.LogRecord], device: str) -> list[logging.LogRecord]:
    return [r for r in records if r.name == RECONNECT_LOG and r.levelno == logging.WARNING and device in r.getMessage()]


def assert_one_line_each_without_traceback(records: list, device: str, crashes: int, says: str, stderr: str) -> None:
    """One warning line per crash naming what is wrong, its traceback only in a debug record, none on stderr."""
    lines = crash_lines(records, device)
    assert len(lines) == crashes
    for line in lines:
        message = line.getMessage()
        assert "\n" not in message and says in message and line.exc_info is None
    assert any(r.levelno == logging.DEBUG and r.exc_info for r in records if r.name == RECONNECT_LOG)
    assert "Traceback" not in stderr


@pytest.mark.parametrize("lie", LIES)
def test_a_stream_whose_metadata_lies_is_a_counted_crash_restarted_with_backoff(lsl, lie, context, caplog, capfd):
    """A driver thread of the compositor (Sources, real time) reading the lying stream: the refusal is a crash,
    counted and restarted again and again with growing waits, its status "crashed" on the bus; the thread lives."""
    caplog.set_level(logging.DEBUG, logger="hmdrt.drivers")
    outlet, url, device = lying_outlet(lsl, lie)
    ingest = context.socket(zmq.SUB)
    ingest.setsockopt(zmq.SUBSCRIBE, b"status.")
    port = ingest.bind_to_random_port("tcp://127.0.0.1")
    sources = Sources([url], MONOTONIC, False, f"tcp://127.0.0.1:{port}", lambda *sample: None)
    said: list[str] = []
    try:
        assert wait_for(lambda: said.extend(states(ingest)) or said.count("crashed") >= 3, timeout_s=15)
        assert any(t.name == f"driver-{device}" and t.is_alive() for t in threading.enumerate())
    finally:
        sources.close()
    del outlet
    counts = sources.counters()[device]
    assert counts["crashes"] >= 3 and counts["samples"] == 0 and said.count("connecting") >= 2  # restarted
    assert sources.hosts[0].reconnect.delay_s > sources.hosts[0].reconnect.first_s  # it waited longer each time
    assert_one_line_each_without_traceback(
        caplog.records, device, counts["crashes"], LIES[lie][1], capfd.readouterr().err
    )


def test_the_run_report_counts_the_crashes_of_each_lying_stream(lsl, tmp_path, context, capfd):
    """A real-time compositor with one driver per lie: the run completes, and its report counts each driver's
    crashes (the threads died uncounted before: `crashes: 0`)."""
    lying = [lying_outlet(lsl, lie) for lie in LIES]
    path = write_config(tmp_path / "run.toml", drivers=[{"url": url} for _, url, _ in lying])
    with compositor(path, context, frames=15, virtual_time=False) as comp:
        report, _ = run_bounded(comp)
    for _, _, device in lying:
        assert report["drivers"][device]["crashes"] >= 1 and report["drivers"][device]["samples"] == 0
    assert report["presented"] >= 1 and "Traceback" not in capfd.readouterr().err


def test_a_stream_whose_info_is_not_what_it_announced_is_refused_before_any_sample(lsl):
    """The inlet reads samples by the channel count and format announced to discovery; a stream info that says
    otherwise (a publisher other than liblsl may answer so) is one error naming the stream and both."""
    announced = lsl.StreamInfo("shifty", "Gaze", 5, 100.0, "double64", "hmdrt-test-shifty")
    for count, channel_format, says in ((6, "double64", "6 of 'double64'"), (5, "float32", "5 of 'float32'")):
        full = lsl.StreamInfo("shifty", "Gaze", count, 100.0, channel_format, "hmdrt-test-shifty")
        with pytest.raises(MetadataError, match=f"'shifty'.*announced 5 channels of 'double64' but .* says {says}"):
            _checked_meta(announced, full)
    many = lsl.StreamInfo("many", "Gaze", 1025, 100.0, "double64", "hmdrt-test-many")
    with pytest.raises(MetadataError, match=r"^LSL stream 'many' \(type 'Gaze', source_id 'hmdrt-test-many', 1025"):
        _checked_meta(many, many)
    assert _checked_meta(announced, announced).channel_count == 5


# --- any driver, any exception ------------------------------------------------------------------------------------


class FaultyDriver(SyntheticDriver):
    """The synthetic device, whose open, read, close and status raise where a test says (counted from 0 over the
    driver's life)."""

    scheme = "faulty"
    faults: dict[str, dict[int, Exception]] = {}  # call: {n: what its n-th call raises}

    def __init__(self, url, clock):
        super().__init__(url, clock)
        self.calls = {"open": 0, "read": 0, "close": 0, "status": 0}
        self.opened_at: list[int] = []

    def _call(self, name: str) -> None:
        n, self.calls[name] = self.calls[name], self.calls[name] + 1
        if n in self.faults.get(name, {}):
            raise self.faults[name][n]

    def open(self) -> None:
        self._call("open")
        self.opened_at.append(self.clock.now_ns())
        super().open()

    def read(self, timeout_s: float) -> list[Sample]:
        self._call("read")
        return super().read(timeout_s)

    def close(self) -> None:
        self._call("close")
        super().close()

    def status(self):
        self._call("status")
        return super().status()


@pytest.fixture
def faulty():
    register("faulty", f"{__name__}:FaultyDriver")
    yield FaultyDriver
    del REGISTRY["faulty"]
    FaultyDriver.faults = {}


def test_a_driver_thread_survives_any_exception_from_any_call(faulty, context, caplog, capfd):
    """Real time: a configuration error and a bug as it opens, a bug as it reads, and a close and a status that
    fail as well are each a counted crash (or, for the close and the status, ignored) and restarted; the samples
    flow again after, and the thread ends only when stopped."""
    caplog.set_level(logging.DEBUG, logger="hmdrt.drivers")
    faulty.faults = {
        "open": {0: MetadataError("the stream lies"), 1: KeyError("a bug as it opens")},
        "read": {20: ValueError("a bug\nover two lines")},
        "close": {0: OSError("and its close fails too")},
        "status": {3: msgspec.ValidationError("and its status")},
    }
    ingest = context.socket(zmq.SUB)
    ingest.setsockopt(zmq.SUBSCRIBE, b"")
    port = ingest.bind_to_random_port("tcp://127.0.0.1")
    sources = Sources(["faulty://?rate=500&name=eye"], MONOTONIC, False, f"tcp://127.0.0.1:{port}", lambda *s: None)
    driver = sources.hosts[0].driver
    try:
        assert wait_for(lambda: len(driver.opened_at) == 2, timeout_s=15)
        restarted = driver.counters.samples
        assert wait_for(lambda: driver.counters.samples > restarted + 50, timeout_s=5)
        assert any(t.name == "driver-eye" and t.is_alive() for t in threading.enumerate())
    finally:
        sources.close()
    assert not any(t.name == "driver-eye" for t in threading.enumerate())
    assert sources.counters()["eye"]["crashes"] == driver.counters.crashes == 3 and len(driver.opened_at) == 2
    lines = [r.getMessage() for r in crash_lines(caplog.records, "eye")]
    assert "MetadataError: the stream lies" in lines[0] and "KeyError: 'a bug as it opens'" in lines[1]
    assert "ValueError: a bug over two lines" in lines[2]
    assert_one_line_each_without_traceback(caplog.records, "eye", 3, "crashed", capfd.readouterr().err)


def test_a_polled_driver_that_raises_is_a_counted_crash_reopened_on_the_virtual_clock(faulty):
    """Virtual time: a read that raises, then an open that raises a configuration error, are crashes reopened
    after the backoff on the virtual clock (0.1 s, then 0.2 s); the frame loop's poll never raises."""
    faulty.faults = {"read": {3: ZeroDivisionError("a bug")}, "open": {1: MetadataError("the stream lies")}}
    clock, got = VirtualClock(), []
    sources = Sources(["faulty://?rate=1000"], clock, True, "", lambda device, sample, now: got.append(now))
    driver = sources.polled[0]
    try:
        for _ in range(60):
            clock.advance(10_000_000)
            sources.poll()
    finally:
        sources.close()
    # read 3 (the second poll's second) crashed at 20 ms; the reopen at 120 ms crashed too; the one 0.2 s later opened
    assert driver.opened_at == [0, 320_000_000]
    assert sources.counters()["faulty"]["crashes"] == 2 and sources.counters()["faulty"]["reconnects"] == 0
    assert got and not any(20_000_000 < t < 320_000_000 for t in got) and max(got) == 600_000_000
