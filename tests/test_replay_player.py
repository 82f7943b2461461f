"""The replay:// player on virtual and real clocks, and the recorder on a real ZeroMQ bus."""

from __future__ import annotations

import math
import threading
import time
from itertools import pairwise
from pathlib import Path

import numpy as np
import pytest
import zmq

from hmdrt.bus.messages import Gaze, Pose, Status, encode
from hmdrt.clock import VirtualClock
from hmdrt.drivers import open_driver
from hmdrt.drivers.host import DriverHost
from hmdrt.errors import ConfigError
from hmdrt.replay.recorder import Recorder
from hmdrt.replay.trace import read_trace, write_trace

from .helpers import wait_for

TRACES = Path(__file__).parent / "data" / "traces"
START_NS = 7_000_000_000  # where the virtual clock stands when the replay opens


def make_trace(path: Path, gaze_period_ms: float = 4.0, count: int = 50) -> list:
    """Gaze at a fixed period with a pose every other gaze; device time lags the trace time by 0.5 ms."""
    t0 = 123_000_000_000
    samples = []
    for k in range(count):
        t = t0 + round(k * gaze_period_ms * 1e6)
        samples.append(Gaze(seq=k, t_host=t, t_dev=t - 500_000, C=(0.0, 0.0, -1.0)))
        if k % 2 == 0:
            samples.append(Pose(seq=k // 2, t_host=t, position=(0.0, 1.6, 0.0), orientation=(1.0, 0.0, 0.0, 0.0)))
    write_trace(path, samples, device="rec")
    return samples


@pytest.mark.parametrize("speed", [1.0, 2.0])
def test_virtual_clock_releases_exactly_the_samples_due(tmp_path, speed):
    samples = make_trace(tmp_path / "t.jsonl")
    t0 = samples[0].t_host
    clock = VirtualClock(START_NS)
    released = []
    with open_driver(f"replay://{tmp_path}/t.jsonl?speed={speed:g}", clock) as driver:
        for now in range(START_NS, START_NS + 250_000_000, 3_000_000):
            clock.advance_to(now)
            got = driver.read(0.1)
            due = [s for s in samples if START_NS + (s.t_host - t0) / speed <= now]
            assert len(released) + len(got) == len(due)
            released += got
    assert len(released) == len(samples) and driver.counters.samples == len(samples)
    for out, original in zip(released, samples, strict=True):
        assert type(out) is type(original) and out.seq == original.seq
        assert out.t_host == START_NS + round((original.t_host - t0) / speed)
        assert out.t_dev == (original.t_host if isinstance(original, Pose) else original.t_dev)


def test_end_of_trace_returns_nothing_and_reports_ended(tmp_path):
    samples = make_trace(tmp_path / "t.jsonl", count=5)
    clock = VirtualClock(START_NS)
    with open_driver(f"replay://{tmp_path}/t.jsonl", clock) as driver:
        clock.advance(10**9)
        assert len(driver.read(0.1)) == len(samples)
        assert driver.read(0.1) == [] and driver.read(0.1) == [] and driver.state == "ended"
        assert driver.status().state == "ended"
    with open_driver(f"replay://{tmp_path}/t.jsonl?speed=0") as driver:  # host clock: waits, no busy loop
        assert len(driver.read(0.0)) == len(samples)
        began, cpu = time.monotonic(), time.thread_time()
        assert driver.read(0.05) == []
        assert time.monotonic() - began >= 0.04 and time.thread_time() - cpu < 0.02  # it slept


def test_loop_continues_with_increasing_times_and_seq(tmp_path):
    period_ms, count = 4.0, 20
    samples = make_trace(tmp_path / "t.jsonl", period_ms, count)
    lap_ns = round(count * period_ms * 1e6)  # span plus one sample period
    clock = VirtualClock(START_NS)
    with open_driver(f"replay://{tmp_path}/t.jsonl?loop=1", clock) as driver:
        clock.advance(3 * lap_ns - 1)
        out = driver.read(0.1)
    assert len(out) == 3 * len(samples) and driver.state != "ended"
    for kind in (Gaze, Pose):
        times = [s.t_host for s in out if isinstance(s, kind)]
        seqs = [s.seq for s in out if isinstance(s, kind)]
        assert all(b > a for a, b in pairwise(times)) and all(b > a for a, b in pairwise(seqs))
    first = [s.t_host for s in out[: len(samples)]]
    assert [s.t_host for s in out[2 * len(samples) :]] == [t + 2 * lap_ns for t in first]


def test_skip_seeks_into_the_trace(tmp_path):
    samples = make_trace(tmp_path / "t.jsonl")
    t0 = samples[0].t_host
    clock = VirtualClock(START_NS)
    with open_driver(f"replay://{tmp_path}/t.jsonl?skip=0.1", clock) as driver:
        first = driver.read(0.1)
        clock.advance(10**9)
        rest = driver.read(0.1)
    kept = [s for s in samples if s.t_host - t0 >= 100_000_000]
    assert len(first + rest) == len(kept) and first
    assert [s.seq for s in first + rest] == [s.seq for s in kept]
    assert all(s.t_host == START_NS for s in first) and first[0].t_dev == kept[0].t_dev
    with pytest.raises(ConfigError, match="past the end"):
        open_driver(f"replay://{tmp_path}/t.jsonl?skip=5").open()


def test_real_time_pacing_over_half_a_second(tmp_path):
    samples = make_trace(tmp_path / "t.jsonl", gaze_period_ms=10.0, count=51)
    arrivals = []
    with open_driver(f"replay://{tmp_path}/t.jsonl") as driver:
        began = time.monotonic_ns()
        while driver.state != "ended" and time.monotonic_ns() - began < 5e9:
            got = driver.read(0.05)
            arrivals += [(s, time.monotonic_ns()) for s in got]
    elapsed_s = (arrivals[-1][1] - began) / 1e9
    assert len(arrivals) == len(samples) and 0.45 <= elapsed_s <= 1.5
    for (out, arrived), original in zip(arrivals, samples, strict=True):
        assert out.t_host <= arrived <= out.t_host + 100_000_000  # never early, at most 100 ms late
        assert out.t_host - arrivals[0][0].t_host == original.t_host - samples[0].t_host


def test_speed_zero_releases_at_once_keeping_the_spacing(tmp_path):
    samples = make_trace(tmp_path / "t.jsonl")
    with open_driver(f"replay://{tmp_path}/t.jsonl?speed=0", VirtualClock(START_NS)) as driver:
        out = driver.read(0.0)
    assert [s.t_host - START_NS for s in out] == [s.t_host - samples[0].t_host for s in samples]


def test_use_source_ts_publishes_the_samples_unchanged(tmp_path):
    samples = make_trace(tmp_path / "t.jsonl")
    with open_driver(f"replay://{tmp_path}/t.jsonl?use_source_ts=1&speed=0", VirtualClock(START_NS)) as driver:
        assert driver.read(0.0) == samples


def test_relative_and_absolute_paths_and_imported_formats(tmp_path, monkeypatch):
    (tmp_path / "Sub").mkdir()
    make_trace(tmp_path / "Sub" / "T.jsonl")
    monkeypatch.chdir(tmp_path)
    for url in ("replay://Sub/T.jsonl?speed=0", f"replay://{tmp_path}/Sub/T.jsonl?speed=0"):
        with open_driver(url, VirtualClock()) as driver:
            assert len(driver.read(0.0)) > 0
    asc = TRACES / "raccoons.asc"
    lines = sum(line[:1].isdigit() for line in asc.read_text(errors="replace").splitlines())
    with open_driver(f"replay://{asc}?speed=0&name=eyelink", VirtualClock()) as driver:
        out = driver.read(0.0)
    assert len(out) == lines and driver.device == "eyelink" and any(not s.valid for s in out)
    assert driver.counters.invalid == sum(not s.valid for s in out)


def test_format_options_reach_the_importer():
    """A screen twice as far away makes every gaze angle from straight ahead about half as large."""
    asc = TRACES / "raccoons.asc"
    angles = []
    for distance in (600, 1200):
        with open_driver(f"replay://{asc}?speed=0&distance_mm={distance}", VirtualClock()) as driver:
            valid = [s for s in driver.read(0.0) if s.valid]
        angles.append(np.array([math.degrees(math.acos(-s.L[2])) for s in valid]))
    moved = angles[0] > 2.0
    assert moved.any() and np.all(angles[1][moved] < 0.6 * angles[0][moved])
    with pytest.raises(ConfigError, match="takes no option 'min_confidence'"):
        open_driver(f"replay://{asc}?min_confidence=0.5").open()


@pytest.mark.parametrize(
    "url, message",
    [
        ("replay://?speed=1", "needs a trace file"),
        ("replay://t.jsonl?speed=-1", r"outside \[0.0, 1000.0\]"),
        ("replay://t.jsonl?loop=1&pace=2", "no option 'pace'"),
    ],
)
def test_bad_replay_urls_quote_the_grammar(url, message):
    with pytest.raises(ConfigError, match=message):
        open_driver(url)


def test_missing_or_foreign_files_fail_at_open(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        open_driver(f"replay://{tmp_path}/none.jsonl").open()
    (tmp_path / "notes.txt").write_text("hello\n")
    with pytest.raises(ConfigError, match="not a trace format"):
        open_driver(f"replay://{tmp_path}/notes.txt").open()


def start_recorder(path: Path, ctx: zmq.Context) -> tuple[Recorder, threading.Event, threading.Thread]:
    recorder = Recorder("tcp://127.0.0.1:*", path, context=ctx)
    stop = threading.Event()
    thread = threading.Thread(target=recorder.run, args=(stop,))
    thread.start()
    return recorder, stop, thread


def record_host(url: str, path: Path, ctx: zmq.Context, duration_s: float) -> tuple[int, Recorder]:
    """Run a DriverHost for url into a fresh Recorder; returns the samples the host sent and the recorder."""
    recorder, stop, thread = start_recorder(path, ctx)
    try:
        host = DriverHost(url, recorder.endpoint, status_period_s=0.2, context=ctx)
        assert recorder.connected.wait(10)  # the host's PUB has joined: nothing it sends from now is lost
        sent = host.run(duration_s=duration_s).samples
        assert wait_for(lambda: recorder.counts.gaze + recorder.counts.pose == sent)
    finally:
        stop.set()
        thread.join()
    return sent, recorder


def test_record_then_replay_round_trips_exactly(tmp_path):
    ctx = zmq.Context()
    try:
        sent, first = record_host("synthetic://?seed=4&rate=250", tmp_path / "a.jsonl", ctx, 1.0)
        original = read_trace(tmp_path / "a.jsonl")
        assert original.device == "synthetic" and original.malformed == 0 and first.counts.status >= 3
        assert len(original.samples) == sent and 150 <= first.counts.gaze <= 300 and first.counts.pose > 0
        url = f"replay://{tmp_path}/a.jsonl?use_source_ts=1&speed=0"
        resent, second = record_host(url, tmp_path / "b.jsonl", ctx, 0.3)
        replayed = read_trace(tmp_path / "b.jsonl")
    finally:
        ctx.destroy(linger=0)
    assert resent == len(original.samples) and replayed.malformed == 0
    assert replayed.samples == original.samples


def test_recorder_counts_malformed_messages_and_flushes_as_it_goes(tmp_path):
    ctx = zmq.Context()
    recorder, stop, thread = start_recorder(tmp_path / "r.jsonl", ctx)
    pub = ctx.socket(zmq.PUB)
    try:
        pub.connect(recorder.endpoint)
        assert recorder.connected.wait(10)
        probe = encode(Status(device="eye", state="connected", t_host=0), "eye")

        def subscribed() -> bool:  # the recorder's subscription reaches the PUB a moment after the handshake
            pub.send_multipart(probe)
            return recorder.counts.status > 0

        assert wait_for(subscribed)
        gaze = Gaze(seq=0, t_host=5, C=(0.0, 0.0, -1.0))
        topic, payload = encode(gaze, "eye")
        bad = [[topic], [topic, b"\xc1"], [b"pose.eye", payload], [b"gaze.", payload], [topic, payload, b"x"]]
        for frames in bad:
            pub.send_multipart(frames)
        pub.send_multipart([topic, payload])
        pub.send_multipart(encode(gaze, "other"))
        pub.send_multipart([b"frame", b"not subscribed"])
        assert wait_for(lambda: recorder.counts.gaze == 1 and recorder.counts.ignored == 1)
        assert recorder.counts.malformed == len(bad)
        assert read_trace(tmp_path / "r.jsonl").samples == [gaze]  # on disk while the recorder still runs
    finally:
        stop.set()
        thread.join()
        pub.close(0)
        ctx.term()
    assert read_trace(tmp_path / "r.jsonl").device == "eye"


def test_recorder_refuses_gzip_and_leaves_a_valid_empty_trace(tmp_path):
    with pytest.raises(ConfigError, match="plain .jsonl"):
        Recorder("tcp://127.0.0.1:*", tmp_path / "r.jsonl.gz")
    with Recorder("tcp://127.0.0.1:*", tmp_path / "r.jsonl") as recorder:
        counts = recorder.run(duration_s=0.05)
    assert counts.gaze == counts.pose == 0 and read_trace(tmp_path / "r.jsonl").samples == []
