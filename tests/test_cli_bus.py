"""`hmdrt emulate`, `hmdrt driver` and `hmdrt record` as a user runs them, over real sockets and processes."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading

import pytest

from hmdrt.bus.messages import Gaze, Pose
from hmdrt.drivers.emulators.smi_server import SmiEmulator
from hmdrt.drivers.host import DriverHost
from hmdrt.replay import load_trace
from hmdrt.replay.recorder import Recorder
from hmdrt.testing import free_port

from .helpers import wait_for


def start(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "hmdrt", *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )


def finish(process: subprocess.Popen, timeout_s: float = 60) -> tuple[str, str]:
    out, err = process.communicate(timeout=timeout_s)
    assert process.returncode == 0, err
    return out, err


def test_driver_publishes_what_record_writes(tmp_path):
    bus, out = f"tcp://127.0.0.1:{free_port()}", tmp_path / "rec.jsonl"
    recorder = start("record", "--out", str(out), "--bus", bus)
    assert "recording" in recorder.stdout.readline()
    driver = start("driver", "synthetic://?seed=3&rate=250&name=eye", "--bus", bus, "--duration", "2")
    driver_out, _ = finish(driver)
    recorder.send_signal(signal.SIGINT)
    recorder_out, _ = finish(recorder)
    reading = load_trace(out)
    gaze = [s for s in reading.samples if isinstance(s, Gaze)]
    poses = [s for s in reading.samples if isinstance(s, Pose)]
    assert reading.device == "eye" and reading.malformed == 0
    assert 400 <= len(gaze) <= 510 and len(poses) == len(gaze)
    assert [g.seq for g in gaze] == list(range(gaze[0].seq, gaze[0].seq + len(gaze)))  # nothing lost on the way
    assert f"{len(gaze)} gaze, {len(poses)} pose (eye)" in recorder_out
    assert "0 dropped" in driver_out


def test_emulate_serves_a_tracker_the_driver_connects_to(tmp_path):
    emulator = start("emulate", "smi", "--port", "0", "--synthetic", "5", "--noise", "0.2")
    line = emulator.stdout.readline()
    url = line.split("hmdrt driver ")[1].strip().strip("'")
    assert url.startswith("smi://127.0.0.1:") and "listen=0" in url
    bus, out = f"tcp://127.0.0.1:{free_port()}", tmp_path / "smi.jsonl"
    recorder, recorded = Recorder(bus, out), threading.Event()
    thread = threading.Thread(target=recorder.run, args=(recorded,))
    thread.start()
    driver_out, _ = finish(start("driver", url, "--bus", bus, "--duration", "1.5"))
    recorded.set()
    thread.join()
    emulator.send_signal(signal.SIGTERM)
    finish(emulator, 10)
    gaze = load_trace(out).samples
    assert 250 <= len(gaze) <= 400 and all(isinstance(g, Gaze) for g in gaze)
    assert all(g.t_dev is not None for g in gaze) and any(g.valid for g in gaze)
    assert "0 malformed" in driver_out


def test_host_reconnects_to_a_restarted_tracker(tmp_path):
    """The emulator goes away mid-stream and comes back on the same port: the host counts a reconnect
    and samples flow again, without the driver process being restarted."""
    port = free_port()
    bus, out = f"tcp://127.0.0.1:{free_port()}", tmp_path / "reconnect.jsonl"
    recorder, stop = Recorder(bus, out), threading.Event()
    rec = threading.Thread(target=recorder.run, args=(stop,))
    rec.start()
    emulator = SmiEmulator(port=port).start()
    counters = []

    def run() -> None:
        host = DriverHost(f"smi://127.0.0.1:{port}?listen=0", bus, backoff_s=(0.1, 0.4))
        counters.append(host.run(stop))

    host_thread = threading.Thread(target=run)
    host_thread.start()
    assert wait_for(lambda: recorder.counts.gaze > 100)
    emulator.stop()
    before = recorder.counts.gaze
    emulator = SmiEmulator(port=port).start()
    assert wait_for(lambda: recorder.counts.gaze > before + 100, timeout_s=15)
    stop.set()
    host_thread.join()
    emulator.stop()
    rec.join()
    assert counters[0].reconnects >= 1 and counters[0].malformed == 0
    assert recorder.counts.status >= 3  # connecting, connected, lost, ... were published


@pytest.mark.parametrize(
    "args, message",
    [
        (["driver", "bogus://x"], "no driver for bogus://"),
        (["driver", "synthetic://?rate=0"], "outside"),
        (["driver", "synthetic://", "--duration", "-1"], "argument --duration: must be positive, got -1"),
        (["record", "--out", "x.jsonl", "--duration", "nan"], "argument --duration: must be positive, got nan"),
        (["emulate", "razor", "--trace", "x.jsonl"], "takes no --trace"),
        (["emulate", "smi", "--port", "70000"], "--port must be within"),
        (["emulate", "smi", "--trace", "missing.jsonl"], "trace not found"),
        (["emulate", "pupil", "--noise", "nan"], "--noise must be within"),
        (["record", "--out", "x.jsonl.gz", "--duration", "1"], "plain .jsonl"),
        (["record", "--out", "x.jsonl", "--bus", "nonsense"], "cannot bind"),
    ],
)
def test_bad_input_gives_one_clear_line(tmp_path, args, message):
    r = subprocess.run([sys.executable, "-m", "hmdrt", *args], capture_output=True, text=True, cwd=tmp_path, timeout=60)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and message in lines[0], r.stderr
