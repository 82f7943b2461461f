"""Soak: the compositor for a long run while its gaze driver is killed and restarted and a fuzzing publisher
floods its ingest with garbage.

    python bench/soak.py [--duration 600] [--kill-every 20] [--down 2] [--fuzz-rate 200] [--json OUT]

The compositor runs as `hmdrt run` in its own process on a config like configs/default.toml (rrm, both
eyes, sim-cpu, 30 Hz, real time) without drivers of its own; a `hmdrt driver replay://...` process
publishes the bundled synthetic trace and is SIGKILLed every --kill-every seconds, then started again
--down seconds later; this script publishes --fuzz-rate messages a second of random bytes, bad msgpack,
wrong types, NaN gaze, unknown schema versions, oversized payloads and invented device names. At the end
the compositor gets SIGTERM and its run report is read. Printed: frames presented, frames out of order
(must be 0), compositor crashes (must be 0), samples dropped by cause, the compositor's RSS after
start-up and at the end, and the gaze outages detected and recovered.
"""

from __future__ import annotations

import argparse
import json
import random
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import msgpack
import zmq

sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

ROOT = Path(__file__).resolve().parent.parent
TRACE = ROOT / "configs" / "traces" / "synthetic_250hz.jsonl.gz"
CONFIG = """scene = "whitted"
[display]
profile = "sim-cpu"
eyes = "both"
[method]
name = "rrm"
[bus]
ingest = "{ingest}"
telemetry = "tcp://127.0.0.1:{telemetry}"
[run]
kernel_threads = 1
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def junk(rng: random.Random) -> list[bytes]:
    """One bad bus message, of a random kind."""
    device = f"fuzz{rng.randrange(1000)}".encode()
    kind = rng.randrange(7)
    if kind == 0:
        return [rng.randbytes(rng.randrange(1, 40)), rng.randbytes(rng.randrange(0, 200))]
    if kind == 1:
        return [b"gaze." + device, rng.randbytes(rng.randrange(1, 100))]
    if kind == 2:
        return [b"gaze." + device, msgpack.packb({"v": 1, "seq": "x", "t_host": [], "C": {"a": 1}})]
    if kind == 3:
        return [b"gaze." + device, msgpack.packb({"v": 1, "seq": 1, "t_host": 1, "C": [float("nan"), 0.0, -1.0]})]
    if kind == 4:
        return [b"pose." + device, msgpack.packb({"v": 99, "seq": 1, "t_host": 1})]
    if kind == 5:
        return [b"gaze." + device, b"\x00" * (1 << 20)]  # over the payload cap
    return [b"gaze." + device, b"x", b"a third frame"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--kill-every", type=float, default=20.0)
    ap.add_argument("--down", type=float, default=2.0, help="seconds the driver stays dead")
    ap.add_argument("--fuzz-rate", type=float, default=200.0, help="bad messages per second")
    ap.add_argument("--json", help="also write the figures here")
    args = ap.parse_args()

    work = Path(tempfile.mkdtemp(prefix="hmdrt-soak-"))
    ingest = f"tcp://127.0.0.1:{free_port()}"
    config = work / "soak.toml"
    config.write_text(CONFIG.format(ingest=ingest, telemetry=free_port()))
    report_path = work / "report.json"
    python = sys.executable
    compositor = subprocess.Popen(
        [python, "-m", "hmdrt", "run", str(config), "--report", str(report_path)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    line = compositor.stdout.readline()
    if not line.startswith("hmdrt run"):
        raise SystemExit(f"the compositor did not start: {line}{compositor.stderr.read()}")
    time.sleep(2.0)  # past the warm-up frames
    rss_start = rss_kib(compositor.pid)

    def driver() -> subprocess.Popen:
        return subprocess.Popen(
            [python, "-m", "hmdrt", "driver", f"replay://{TRACE}?loop=1", "--bus", ingest],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )

    context = zmq.Context()
    fuzz = context.socket(zmq.PUB)
    fuzz.setsockopt(zmq.SNDHWM, 1000)
    fuzz.connect(ingest)
    rng = random.Random(1)
    started = time.monotonic()
    proc, kills, sent = driver(), 0, 0
    next_kill, restart_at = started + args.kill_every, None
    crashed = False
    try:
        while time.monotonic() - started < args.duration:
            now = time.monotonic()
            if proc is not None and now >= next_kill:
                proc.send_signal(signal.SIGKILL)
                proc.wait()
                proc, kills, restart_at = None, kills + 1, now + args.down
                next_kill = now + args.kill_every
            if proc is None and restart_at is not None and now >= restart_at:
                proc, restart_at = driver(), None
            try:
                fuzz.send_multipart(junk(rng), flags=zmq.NOBLOCK)
                sent += 1
            except zmq.Again:
                pass
            if compositor.poll() is not None:
                crashed = True
                break
            time.sleep(1.0 / args.fuzz_rate)
        rss_end = rss_kib(compositor.pid) if not crashed else 0
    finally:
        if proc is not None:
            proc.kill()
            proc.wait()
        fuzz.close(0)
        context.term()
        if compositor.poll() is None:
            compositor.send_signal(signal.SIGTERM)
        _, stderr = compositor.communicate(timeout=120)
    crashed = crashed or compositor.returncode != 0 or "Traceback" in stderr
    report = json.loads(report_path.read_text()) if report_path.exists() else {}
    drops: dict[str, int] = {"ingest_malformed": report.get("ingest_malformed", 0)}
    drops["devices_refused"] = report.get("devices_refused", 0)
    for counts in report.get("samples", {}).values():
        for cause in ("duplicates", "too_old", "ahead", "malformed", "evicted"):
            drops[cause] = drops.get(cause, 0) + counts.get(cause, 0)
    outages = report.get("outages", {})
    figures = {
        "duration_s": round(time.monotonic() - started, 1),
        "frames_presented": report.get("presented"),
        "vsyncs": report.get("vsyncs"),
        "out_of_order": report.get("out_of_order"),
        "compositor_crashes": int(crashed),
        "driver_kills": kills,
        "fuzz_messages_sent": sent,
        "dropped_by_cause": drops,
        "rss_kib_start": rss_start,
        "rss_kib_end": rss_end,
        "rss_growth_kib": rss_end - rss_start,
        "outages_detected": outages.get("count"),
        "outages_recovered": outages.get("recovered"),
        "miss_rate": report.get("miss_rate"),
    }
    print(f"soak: {figures['duration_s']} s, driver killed {kills} times, {sent} bad messages published")
    print(f"  frames presented {figures['frames_presented']} of {figures['vsyncs']} VSyncs; out of order "
          f"{figures['out_of_order']}; compositor crashes {figures['compositor_crashes']}")  # fmt: skip
    print(f"  dropped by cause: {drops}")
    print(f"  RSS {rss_start / 1024:.1f} MiB after start-up, {rss_end / 1024:.1f} MiB at the end "
          f"({(rss_end - rss_start) / 1024:+.1f} MiB)")  # fmt: skip
    print(f"  gaze outages detected {figures['outages_detected']}, recovered {figures['outages_recovered']}")
    if crashed:
        print(stderr[-2000:], file=sys.stderr)
    if args.json:
        Path(args.json).write_text(json.dumps(figures, indent=2) + "\n")


if __name__ == "__main__":
    main()
