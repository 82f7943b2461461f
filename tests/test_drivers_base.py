"""The driver interface, registry, clock sync, synthetic driver and driver host on a real ZeroMQ bus."""

from __future__ import annotations

import threading

import numpy as np
import pytest
import zmq

from hmdrt.bus.messages import Gaze, MalformedMessage, Pose, Status, decode, encode, usable
from hmdrt.clock import VirtualClock
from hmdrt.drivers import REGISTRY, DriverNotFound, driver_class, open_driver, register
from hmdrt.drivers.base import SequenceGaps
from hmdrt.drivers.clocksync import ClockSync
from hmdrt.drivers.host import DriverHost
from hmdrt.drivers.synthetic import SyntheticDriver
from hmdrt.errors import ConfigError


def test_registry_resolves_every_scheme_to_a_driver_class():
    for scheme in REGISTRY:
        cls = driver_class(scheme)
        assert cls.scheme == scheme and cls.grammar.startswith(scheme + "://")


def test_unknown_scheme_lists_the_known_ones():
    with pytest.raises(DriverNotFound, match="synthetic://"):
        open_driver("bogus://x")


def test_register_adds_a_scheme():
    register("synthetic2", "hmdrt.drivers.synthetic:SyntheticDriver")
    try:
        assert isinstance(open_driver("synthetic2://?seed=3"), SyntheticDriver)
    finally:
        del REGISTRY["synthetic2"]


@pytest.mark.parametrize(
    "url, message",
    [
        ("synthetic://?sed=1", "no option 'sed'"),
        ("synthetic://?rate=fast", "rate='fast' is not a float"),
        ("synthetic://?rate=0", r"outside \[1.0, 10000.0\]"),
        ("synthetic://?noise=nan", "must be finite"),
        ("no-scheme", "needs a scheme"),
        ("synthetic://?seed", "bad query"),
        ("synthetic://?device_latency=-1", r"outside \[0.0, 10000.0\]"),
        ("smi://127.0.0.1:port", "port must be a number"),
    ],
)
def test_bad_url_options_are_clear_errors(url, message):
    with pytest.raises(ConfigError, match=message):
        driver = open_driver(url)
        assert driver.url.port is not None  # a port that is not a number raises here at the latest


def test_sequence_gaps_count_lost_frames_across_wrap():
    gaps = SequenceGaps(modulus=2**16)
    for seq in (65533, 65534, 1, 2, 5):
        gaps.see(seq)
    assert gaps.lost == 2 + 2  # 65535 and 0, then 3 and 4
    assert gaps.see(5) == 0  # a repeat is not a loss


def _pairs(offset_ns, drift_ppm, jitter_ms, seconds, rate_hz=250, seed=0, t0=0):
    rng = np.random.default_rng(seed)
    t_dev = t0 + np.arange(int(seconds * rate_hz)) * int(1e9 / rate_hz)
    capture_host = t_dev + offset_ns + drift_ppm * 1e-6 * (t_dev - t0)
    recv = capture_host + 200_000 + rng.exponential(jitter_ms * 1e6 / 3, t_dev.size)
    return t_dev.astype(np.int64), capture_host, recv.astype(np.int64)


def test_clock_sync_tracks_offset_and_drift_under_jitter():
    sync = ClockSync()
    t_dev, truth, recv = _pairs(5_000_000_000, 50, 2.0, 30)
    errors = [sync.add(int(d), int(r)) - c for d, c, r in zip(t_dev, truth, recv, strict=True)]
    late = np.abs(np.array(errors[-2500:]) - 200_000)  # the latency floor is not observable: a constant
    assert np.percentile(late, 99) < 500_000
    est = sync.estimate()
    assert abs(est.drift_ppm - 50) < 10 and est.residual_ns < 500_000 and est.pairs == t_dev.size


def test_clock_sync_unwraps_a_wrapping_counter():
    wrap = 2**32 * 1000  # a 32-bit microsecond counter, in ns
    sync = ClockSync(wrap_ns=wrap)
    t_dev, truth, recv = _pairs(0, 0, 0.5, 4, t0=wrap - 2_000_000_000)
    hosts = [sync.add(int(d) % wrap, int(r)) for d, r in zip(t_dev, recv, strict=True)]
    assert np.all(np.diff(hosts) > 0)  # no jump backwards at the wrap
    assert abs(hosts[-1] - truth[-1]) < 1_000_000


def test_clock_sync_restarts_after_a_device_reset():
    sync = ClockSync()
    t_dev, _, recv = _pairs(10_000_000_000, 0, 0.5, 3)
    for d, r in zip(t_dev, recv, strict=True):
        sync.add(int(d), int(r))
    # the device restarts its clock at zero one second later
    restart = recv[-1] + 1_000_000_000
    t_dev2, truth2, recv2 = _pairs(int(restart), 0, 0.5, 3)
    hosts = [sync.add(int(d), int(r)) for d, r in zip(t_dev2, recv2, strict=True)]
    assert sync.resets == 1
    assert abs(hosts[-1] - truth2[-1]) < 1_000_000


def test_clock_sync_ignores_a_host_stall_and_never_maps_after_receipt():
    sync = ClockSync()
    t_dev, truth, recv = _pairs(0, 50, 2.0, 10)
    recv[1000:1100] += 300_000_000  # the host stalls for 0.3 s: 400 ms of samples arrive late
    hosts = np.array([sync.add(int(d), int(r)) for d, r in zip(t_dev, recv, strict=True)])
    assert np.all(hosts <= recv)
    late = np.abs(hosts[-250:] - truth[-250:] - 200_000)
    assert late.max() < 500_000 and abs(sync.estimate().drift_ppm - 50) < 10


def test_clock_sync_fits_no_drift_from_a_short_span():
    sync = ClockSync()
    t_dev, _, recv = _pairs(0, 0, 2.0, 0.5, seed=3)
    for d, r in zip(t_dev, recv, strict=True):
        sync.add(int(d), int(r))
    assert sync.estimate().drift_ppm == 0.0


def test_clock_sync_round_trip_probe_removes_the_latency_floor():
    sync = ClockSync()
    offset = 7_000_000_000
    sync.probe(t_send=offset + 1_000_000, t_dev_raw=1_000_000 + 150_000, t_reply=offset + 1_300_000)
    t_dev, truth, recv = _pairs(offset, 0, 1.0, 3)  # recv = capture + 0.2 ms floor + jitter
    hosts = [sync.add(int(d), int(r)) for d, r in zip(t_dev, recv, strict=True)]
    assert abs(hosts[-1] - truth[-1]) < 50_000  # the floor is gone, not just held constant
    assert abs(sync.estimate().floor_ns - 200_000) < 50_000


def test_clock_sync_with_one_pair_uses_its_delay():
    sync = ClockSync()
    assert sync.estimate() is None
    assert sync.add(1000, 5000) == 5000
    assert sync.estimate().offset_ns == 4000


def test_synthetic_driver_follows_a_virtual_clock():
    clock = VirtualClock(1_000_000_000)
    with open_driver("synthetic://?seed=2&rate=100&head=0", clock) as driver:
        first = driver.read(0.1)  # only what is due at the current instant; the clock does not move
        clock.advance(1_000_000_000)
        later = driver.read(0.1)
    assert len(first) <= 1 and 99 <= len(later) <= 101
    assert all(isinstance(s, Gaze) and 1_000_000_000 <= s.t_host <= clock.now_ns() for s in first + later)
    assert driver.counters.samples == len(first) + len(later) == driver.status().samples


def test_bus_messages_round_trip_and_reject_garbage():
    gaze = Gaze(seq=3, t_host=10, L=(0.0, 0.0, -1.0), R=(0.0, 0.0, -1.0), depth_m=1.2)
    assert decode(encode(gaze, "eye")) == ("gaze", "eye", gaze)
    pose = Pose(seq=1, t_host=5, position=(0.0, 1.6, 0.0), orientation=(1.0, 0.0, 0.0, 0.0))
    assert decode(encode(pose, "head"))[2] == pose and usable(pose)
    topic, payload = encode(gaze, "eye")
    for frames in ([topic], [b"pose.eye", payload], [topic, b"\xc1"], [topic, payload + b"x" * 70_000]):
        with pytest.raises(MalformedMessage):
            decode(frames)
    assert not usable(Gaze(seq=0, t_host=0, C=(0.0, 0.0, -0.5)))


@pytest.fixture
def ingest():
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    port = sub.bind_to_random_port("tcp://127.0.0.1")
    yield ctx, sub, f"tcp://127.0.0.1:{port}"
    sub.close(0)
    ctx.term()


def collect(sub, until: threading.Event, timeout_s: float = 5.0) -> list:
    got = []
    poller = zmq.Poller()
    poller.register(sub, zmq.POLLIN)
    idle = 0
    while idle < timeout_s * 20:
        if poller.poll(50):
            got.append(decode(sub.recv_multipart()))
            idle = 0
        elif until.is_set():
            idle += 1 if idle < 4 else timeout_s * 20
        else:
            idle += 1
    return got


def test_host_publishes_samples_and_status_on_a_real_bus(ingest):
    ctx, sub, endpoint = ingest
    done, counters = threading.Event(), []

    def run() -> None:  # the host waits for the subscription, which arrives only while collect() polls
        host = DriverHost("synthetic://?seed=1&rate=250&name=eye0", endpoint, status_period_s=0.2, context=ctx)
        counters.append(host.run(duration_s=1.0))
        done.set()

    runner = threading.Thread(target=run)
    runner.start()
    got = collect(sub, done)
    runner.join()
    kinds = [kind for kind, _, _ in got]
    assert {device for _, device, _ in got} == {"eye0"}
    gazes = [m for k, _, m in got if k == "gaze"]
    assert 150 <= len(gazes) <= 260 and kinds.count("pose") == len(gazes)
    assert [g.seq for g in gazes] == sorted(g.seq for g in gazes)
    statuses = [m for k, _, m in got if k == "status"]
    assert isinstance(statuses[-1], Status) and statuses[-1].state == "closed"
    assert {"connecting", "connected"} <= {s.state for s in statuses} and len(statuses) >= 5
    assert statuses[-1].samples == counters[0].samples and counters[0].dropped == 0
