"""Faults and overload: a silent gaze tracker, a killed driver process, a crashing driver, a killed
recorder, a gaze flood and a busy CPU; the compositor keeps presenting in order and counts what happened."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgpack
import pytest
import zmq

from hmdrt.bus.messages import Gaze, encode
from hmdrt.compositor.config import Fallback
from hmdrt.compositor.fallback import GazeFallback, Outages
from hmdrt.compositor.samples import MAX_DEVICES
from hmdrt.drivers.host import DriverHost
from hmdrt.errors import ConfigError
from hmdrt.replay import load_trace
from hmdrt.testing import TRACE, Background, compositor, free_port, write_config

from .compositor_helpers import readline, start_run
from .helpers import reap, wait_for

MS = 1_000_000


def test_an_outage_starts_after_stale_ms_widens_the_fovea_then_falls_back_to_the_centre_and_ends_on_a_sample():
    outages = Outages(Fallback(stale_ms=200, widen_deg_per_s=10, max_widen_deg=5, centre_after_ms=1000))
    assert outages.judge(None, 5_000 * MS).stale is False  # no sample yet: nothing to lose
    assert outages.judge(0, 200 * MS) == GazeFallback(200 * MS, False, 0.0, False)
    fallback = outages.judge(0, 400 * MS)
    assert fallback.stale and fallback.widen_deg == pytest.approx(2.0) and not fallback.centre
    assert outages.judge(0, 900 * MS).widen_deg == 5.0  # capped at max_widen_deg
    assert outages.judge(0, 1001 * MS).centre
    assert (outages.count, outages.widened_frames, outages.centre_frames) == (1, 3, 1)
    assert outages.judge(1500 * MS, 1510 * MS).stale is False  # a sample arrived at 1.5 s: over
    report = outages.to_dict()
    assert report["recovered"] == 1 and report["longest_s"] == 1.5 and report["ongoing"] is False
    assert report["outages"] == [{"since_ns": 0, "resumed_ns": 1500 * MS, "seconds": 1.5}]
    outages.judge(1500 * MS, 1800 * MS)
    assert outages.count == 2 and outages.to_dict()["ongoing"] is True


def test_a_centre_fallback_sooner_than_the_stale_time_is_a_config_error():
    with pytest.raises(ValueError, match="centre_after_ms"):
        Fallback(stale_ms=500, centre_after_ms=100)


def start_driver(url: str, bus: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "hmdrt", "driver", url, "--bus", bus],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_a_killed_driver_process_is_an_outage_the_compositor_presents_through_and_recovers_from(tmp_path, context):
    """SIGKILL the only gaze driver mid-stream: VSyncs go on, the gaze is held and the fovea widened, then the
    screen centre is used; a restarted driver ends the outage, and the report counts it."""
    fallback = {"stale_ms": 150.0, "widen_deg_per_s": 40.0, "max_widen_deg": 10.0, "centre_after_ms": 500.0}
    path = write_config(tmp_path / "outage.toml", eyes="left", drivers=[], fallback=fallback)
    url = f"replay://{TRACE}?loop=1"
    with compositor(path, context, duration_s=120) as comp:
        run = Background(comp)
        driver = start_driver(url, comp.ingest.address)
        try:
            assert wait_for(lambda: sum(r.gaze is not None for r in comp.records) >= 5, timeout_s=30)
            driver.kill()
            driver.wait(10)
            killed = len(comp.records)
            assert wait_for(lambda: comp.outages.centre_frames >= 3, timeout_s=30)
            driver = start_driver(url, comp.ingest.address)
            assert wait_for(lambda: comp.outages.recovered == 1, timeout_s=30)
            resumed = len(comp.records)
            assert wait_for(lambda: any(r.gaze is not None for r in comp.records[resumed:]), timeout_s=30)
        finally:
            driver.kill()
            driver.wait(10)
            comp.stop.set()
        report, _ = run.join(30)
    outage = report["outages"]
    assert outage["count"] == 1 and outage["recovered"] == 1 and outage["ongoing"] is False
    assert outage["longest_s"] >= 0.5 and outage["widened_frames"] >= 1 and outage["centre_frames"] >= 3
    during = comp.records[killed:resumed]
    assert any(r.gaze is None for r in during)  # the screen centre
    assert any(r.params["fovea_deg"] > 10.0 for r in during)  # the configured 10 degrees, widened
    assert report["out_of_order"] == 0 and report["presented"] + report["re_presented"] == report["vsyncs"]


def test_the_driver_host_restarts_a_crashing_driver_with_growing_backoff(context):
    sub = context.socket(zmq.SUB)
    sub.setsockopt(zmq.SUBSCRIBE, b"gaze.")
    port = sub.bind_to_random_port("tcp://127.0.0.1")
    host = DriverHost("synthetic://?rate=500", f"tcp://127.0.0.1:{port}", backoff_s=(0.05, 0.2), context=context)
    read, opened = host.driver.read, []
    open_ = host.driver.open

    def crashing_read(timeout_s):
        if len(opened) <= 3 and host.driver.counters.samples > 10 * len(opened):
            raise ZeroDivisionError("a bug in the driver")
        return read(timeout_s)

    def recording_open():
        opened.append(time.monotonic())
        open_()

    host.driver.read, host.driver.open = crashing_read, recording_open
    stop = threading.Event()
    thread = threading.Thread(target=host.run, args=(stop,))
    thread.start()
    try:
        assert wait_for(lambda: len(opened) >= 4 and host.driver.counters.samples > 50, timeout_s=20)
        assert sub.poll(5000)  # samples still reach the bus after the restarts
    finally:
        stop.set()
        thread.join(10)
        sub.close(0)
    assert host.driver.counters.crashes == 3 and not thread.is_alive()
    gaps = [b - a for a, b in zip(opened, opened[1:4], strict=False)]
    assert gaps[0] >= 0.05 and gaps[1] >= 0.1 and gaps[2] >= 0.2  # 0.05, 0.1, then the 0.2 s ceiling


def test_a_recording_killed_mid_stream_replays_up_to_its_last_complete_line(tmp_path, context):
    out, bus = tmp_path / "rec.jsonl", f"tcp://127.0.0.1:{free_port()}"
    recorder = subprocess.Popen(
        [sys.executable, "-m", "hmdrt", "record", "--out", str(out), "--bus", bus],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    stop = threading.Event()
    try:
        assert readline(recorder, 30).startswith("recording")
        host = DriverHost("synthetic://?rate=1000", bus, context=context)
        thread = threading.Thread(target=host.run, args=(stop,))
        thread.start()

        def lines() -> int:
            return out.read_bytes().count(b"\n") if out.exists() else 0

        assert wait_for(lambda: lines() >= 300, timeout_s=30)  # flushed while recording, not at the end
        recorder.send_signal(signal.SIGKILL)
        recorder.wait(10)
    finally:
        stop.set()
        if recorder.poll() is None:
            recorder.kill()
        recorder.communicate()
    thread.join(10)
    data = out.read_bytes()
    complete = data[: data.rfind(b"\n") + 1]
    reading = load_trace(out)
    assert len(reading.samples) == complete.count(b"\n") - 1  # every complete line but the header
    assert reading.malformed == (0 if data.endswith(b"\n") else 1)  # a cut last line is counted, not fatal


def test_a_gaze_flood_from_many_devices_stays_within_the_stated_memory_bound(tmp_path, context):
    """20,000 gaze messages as fast as they go (about 10 kHz or more), duplicates and out-of-order ones among
    them, from 100 device names: each device keeps at most max_per_device samples, at most MAX_DEVICES devices
    are tracked, the rest are counted, and the compositor keeps presenting."""
    path = write_config(tmp_path / "flood.toml", eyes="left", drivers=[])
    with compositor(path, context, duration_s=120) as comp:
        run = Background(comp)
        pub = context.socket(zmq.PUB)
        pub.setsockopt(zmq.SNDHWM, 0)
        pub.connect(comp.ingest.address)
        try:
            assert wait_for(lambda: len(comp.records) >= 2, timeout_s=30)
            time.sleep(0.3)  # the subscription reaches the PUB
            now = time.monotonic_ns()
            for i in range(20_000):
                seq = i if i % 10 else i - 5  # every tenth goes back in time
                gaze = Gaze(seq=seq, t_host=now + seq * 100_000, t_dev=seq, C=(0.0, 0.0, -1.0))
                pub.send_multipart(encode(gaze, f"d{i % 100}"))
            frames = len(comp.records)
            assert wait_for(lambda: comp.store.devices_refused > 0 and len(comp.records) > frames + 3, timeout_s=30)
        finally:
            pub.close(0)
            comp.stop.set()
        report, _ = run.join(30)
    counts = comp.store.counts()
    assert len(counts) == MAX_DEVICES and report["devices_refused"] > 0
    assert all(c.stored <= comp.store.max_per_device for c in counts.values())
    assert sum(c.samples for c in counts.values()) + report["devices_refused"] + report["ingest_malformed"] > 0
    assert report["out_of_order"] == 0


def test_under_cpu_contention_frames_stay_in_order_and_sigterm_still_writes_a_complete_report(tmp_path):
    config, out = write_config(tmp_path / "busy.toml"), tmp_path / "report.json"
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(os.cpu_count() or 2)]
    process = start_run(config, out)
    try:
        assert readline(process, 120).startswith("hmdrt run")
        time.sleep(3.0)
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=60)
    finally:
        for hog in hogs:
            hog.kill()
            hog.wait()
        reap(process)
    assert process.returncode == 0 and "Traceback" not in stderr, stderr
    report = json.loads(out.read_text())
    assert report["vsyncs"] > 0 and report["presented"] + report["re_presented"] == report["vsyncs"]
    assert report["out_of_order"] == 0
    assert report["deadline_misses"] == report["late"] + report["dropped"]  # every miss is counted once


def test_a_report_path_that_cannot_be_written_is_an_error_at_start(tmp_path, capsys):
    from hmdrt.cli import main

    (tmp_path / "file").write_text("")
    config = write_config(tmp_path / "r.toml", eyes="left")
    started = time.monotonic()
    assert (
        main(["run", str(config), "--frames", "3", "--virtual-time", "--report", str(tmp_path / "file" / "r.json")])
        == 1
    )
    err = capsys.readouterr().err
    assert err.startswith("hmdrt: error: cannot write") and err.count("\n") == 1
    assert time.monotonic() - started < 30


def test_fallback_settings_are_validated_on_load(tmp_path):
    from hmdrt.compositor.config import load_config

    path = write_config(tmp_path / "f.toml", fallback={"stale_ms": 0.0})
    with pytest.raises(ConfigError, match="stale_ms"):
        load_config(Path(path))


@pytest.mark.slow
def test_soak_with_drivers_killed_and_a_fuzzing_publisher_keeps_presenting_in_order(tmp_path):
    """bench/soak.py for 90 s, the driver killed every 10 s: no crash, nothing out of order, every outage seen
    and all but possibly the last recovered, RSS growth within 64 MiB."""
    out = tmp_path / "soak.json"
    bench = Path(__file__).resolve().parent.parent / "bench" / "soak.py"
    run = subprocess.run(
        [sys.executable, str(bench), "--duration", "90", "--kill-every", "10", "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=400,
    )
    assert run.returncode == 0, run.stderr
    figures = json.loads(out.read_text())
    assert figures["compositor_crashes"] == 0 and figures["out_of_order"] == 0
    assert figures["driver_kills"] >= 8 and figures["outages_detected"] >= figures["driver_kills"]
    assert figures["outages_recovered"] >= figures["outages_detected"] - 1
    assert figures["dropped_by_cause"]["ingest_malformed"] > 0
    assert figures["rss_growth_kib"] < 64 * 1024


def test_a_control_request_nested_deeper_than_python_can_decode_is_answered_with_an_error(tmp_path, context):
    """msgspec refuses nesting beyond Python's recursion limit with RecursionError: the control thread answers
    a bad request and counts it, and goes on answering."""
    path = write_config(tmp_path / "deep.toml", eyes="left")
    with compositor(path, context, duration_s=120) as comp:
        sock = context.socket(zmq.REQ)
        sock.connect(comp.control.address)
        try:
            sock.send(b"\x91" * 30_000 + b"\x01")
            assert sock.poll(10_000)
            reply = msgpack.unpackb(sock.recv())
        finally:
            sock.close(0)
        assert reply["ok"] is False and comp.control.bad_requests == 1
        from hmdrt.compositor.endpoints import request

        assert request(comp.control.address, {"cmd": "status"})["method"] == "rrm"


def test_a_driver_name_that_is_not_printable_ascii_is_a_config_error():
    from hmdrt.drivers import open_driver

    with pytest.raises(ConfigError, match="name= must be printable ASCII"):
        open_driver("synthetic://?name=caf%C3%A9")


def test_a_report_snapshot_is_not_changed_by_later_records():
    """summary() copies the report under the lock and works out percentiles after releasing it."""
    from hmdrt.telemetry.report import RunReport

    report = RunReport(30.0)
    snapshot = report.snapshot()
    report.frame_ms.add(12.0)
    report.shown["new"] += 1
    report.stages_ms["trace"] = 3.0
    assert snapshot.frame_ms.n == 0 and snapshot.shown["new"] == 0 and snapshot.stages_ms == {}
    assert snapshot.frame_ms.percentiles()["p50"] is None and report.frame_ms.percentiles()["p50"] == 12.0
    assert snapshot.to_dict()["frames"] == 0 and report.frames == 1
