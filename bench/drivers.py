"""Driver rates, drops and device-to-bus latency on loopback; clock-sync accuracy; fused head orientation.

    python bench/drivers.py [--seconds 10] [--only smi pupil dk2 razor clock fusion]

Rates: each driver runs under a DriverHost (the `hmdrt driver` process's loop) in a process of its own,
against its emulator in another (as a real device would be), publishing to a SUB socket bound in this
one as the compositor's ingest would be: SMI at 250 Hz over UDP,
Pupil at 200 Hz over ZeroMQ, the DK2 stub's 1000 Hz IMU (two samples per report, so 500 poses/s),
Razor at 50 Hz through a pseudo-terminal. Dropped = samples the driver saw missing from the device's
sequence plus those the host could not queue plus gaps in seq on the bus. Added latency = arrival on
the bus minus the moment the emulator wrote the sample to its socket (its `sent` log), so it holds
the socket hop, parsing, conversion, clock sync and publishing. The DK2 stub lives inside the driver
(it is hidapi's device object): its figure starts when a report fell due on the stub's clock. Razor
frames carry no device time: its figure starts at the driver's receipt, after the pseudo-terminal.
All three processes read the one system monotonic clock. The first 0.5 s (connection set-up) is left
out.

Clock sync: 60 s of 250 Hz device timestamps drifting 50 ppm, received with a 0.2 ms latency floor
plus up to 2 ms of jitter (uniform), through ClockSync; the residual is its RMS fit error, the mapping
error is t_host minus the true capture time (less the constant floor, which one-way timestamps
cannot show). Fusion: hid://stub on a virtual clock, 60 s of synthetic head motion; the error is the
angle between fused and true orientation, compared in the world frame the filter set up (yaw 0 where
the head faced when it levelled).
"""

from __future__ import annotations

import argparse
import multiprocessing
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zmq

# this script shares the drivers package's name: keep its own folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from hmdrt.bus.messages import decode  # noqa: E402
from hmdrt.drivers import open_driver  # noqa: E402
from hmdrt.drivers.clocksync import ClockSync  # noqa: E402
from hmdrt.drivers.emulators.dk2_stub import HeadMotion  # noqa: E402
from hmdrt.drivers.emulators.pupil_server import PupilEmulator  # noqa: E402
from hmdrt.drivers.emulators.serial_emulator import SerialTrackerEmulator  # noqa: E402
from hmdrt.drivers.emulators.smi_server import SmiEmulator  # noqa: E402
from hmdrt.drivers.host import DriverHost  # noqa: E402
from hmdrt.spatial import quat_multiply  # noqa: E402

WARMUP_NS = 500_000_000


class Bus:
    """The compositor's side of the ingest: a bound SUB recording (arrival ns, kind, message)."""

    def __init__(self, ctx: zmq.Context):
        self.sub = ctx.socket(zmq.SUB)
        self.sub.setsockopt(zmq.SUBSCRIBE, b"")
        self.sub.setsockopt(zmq.RCVHWM, 1_000_000)
        self.endpoint = f"tcp://127.0.0.1:{self.sub.bind_to_random_port('tcp://127.0.0.1')}"

    def record(self, seconds: float) -> list[tuple[int, str, object]]:
        got = []
        end = time.monotonic_ns() + int(seconds * 1e9)
        while time.monotonic_ns() < end:
            if self.sub.poll(20):
                while True:
                    try:
                        frames = self.sub.recv_multipart(zmq.NOBLOCK)
                    except zmq.Again:
                        break
                    kind, _, message = decode(frames)
                    got.append((time.monotonic_ns(), kind, message))
        return got


def serve_emulator(make, pipe) -> None:
    """Child process: the emulated device, reporting its driver URL and, when told to stop, its send log."""
    with make() as emulator:
        pipe.send(emulator.url)
        pipe.recv()
    pipe.send(list(emulator.sent))


def host_driver(url: str, endpoint: str, stop, pipe) -> None:
    """Child process: `hmdrt driver URL --bus ENDPOINT`'s loop, reporting its counters when stopped."""
    host = DriverHost(url, endpoint, context=zmq.Context())
    reporter = threading.Thread(target=lambda: pipe.send(stub_epoch(host)), daemon=True)
    reporter.start()
    pipe.send(host.run(stop))


def stub_epoch(host: DriverHost) -> int | None:
    """The hid:// stub's clock epoch, once the driver has opened it (None for other drivers)."""
    if host.driver.scheme != "hid":
        return None
    while host.driver.hid is None:
        time.sleep(0.01)
    return host.driver.hid.epoch_ns


def run_driver(name: str, device, kind: str, rate_hz: float, seconds: float, ctx: zmq.Context) -> dict:
    """One driver under a DriverHost in its own process against `device` (a driver URL, or a factory of
    an emulator served from a third process) for `seconds`; rate, drops and latency of its `kind` samples."""
    mp = multiprocessing.get_context("fork")
    emulator = None
    if callable(device):
        mine, theirs = mp.Pipe()
        emulator = mp.Process(target=serve_emulator, args=(device, theirs))
        emulator.start()
        url = mine.recv()
    else:
        url = device
    bus = Bus(ctx)
    stop, (results, sink) = mp.Event(), mp.Pipe()
    host = mp.Process(target=host_driver, args=(url, bus.endpoint, stop, sink))
    host.start()
    got = [(t, m) for t, k, m in bus.record(seconds) if k == kind]
    stop.set()
    stub_epoch = results.recv()
    counters = results.recv()
    host.join()
    bus.sub.close(0)
    sent = {}
    if emulator is not None:
        mine.send("stop")
        sent = {t_dev // 1000: t for t_dev, t in mine.recv()}  # device time in us -> when it went out
        emulator.join()
    seqs = np.array([m.seq for _, m in got])
    gaps = int(np.sum(np.diff(seqs) - 1)) if len(seqs) > 1 else 0
    steady = [(t, m) for t, m in got if t - got[0][0] >= WARMUP_NS]
    if sent:
        latency, origin = [t - sent[m.t_dev // 1000] for t, m in steady], "emulator send"
    elif stub_epoch is not None:
        latency, origin = [t - (stub_epoch + m.t_dev) for t, m in steady], "stub report due"
    else:
        latency, origin = [t - m.t_host for t, m in steady], "driver receipt"
    latency = np.array(latency) / 1e6
    return {
        "driver": name,
        "expected_hz": rate_hz,
        "measured_hz": (len(steady) - 1) / ((steady[-1][0] - steady[0][0]) / 1e9),
        "samples": len(got),
        "dropped": counters.dropped + gaps,
        "malformed": counters.malformed,
        "p50_ms": float(np.percentile(latency, 50)),
        "p99_ms": float(np.percentile(latency, 99)),
        "max_ms": float(latency.max()),
        "from": origin,
    }


def driver_rows(seconds: float, only: set[str]) -> list[dict]:
    devices = {
        "smi": ("smi", lambda: SmiEmulator(rate_hz=250), "gaze", 250),
        "pupil": ("pupil", lambda: PupilEmulator(rate_hz=200), "gaze", 200),
        "dk2": ("dk2 (hid://stub)", "hid://stub?device=dk2", "pose", 500),
        "razor": ("razor (pty)", lambda: SerialTrackerEmulator("razor"), "pose", 50),
    }
    ctx = zmq.Context()
    rows = [run_driver(*spec[:4], seconds, ctx) for key, spec in devices.items() if key in only]
    ctx.term()
    return rows


def clock_sync(seconds: float = 60.0, rate_hz: float = 250.0, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    n = int(seconds * rate_hz)
    t_dev = np.arange(n, dtype=np.int64) * int(1e9 / rate_hz)
    capture = 3_000_000_000_000 + t_dev + (50e-6 * t_dev).astype(np.int64)
    floor = 200_000
    recv = capture + floor + rng.uniform(0, 2_000_000, n).astype(np.int64)
    sync = ClockSync()
    mapped = np.array([sync.add(int(d), int(r)) for d, r in zip(t_dev, recv, strict=True)])
    error = np.abs(mapped - capture - floor)[n // 10 :] / 1e6  # after the first tenth: the estimate has settled
    est = sync.estimate()
    return {
        "residual_ms": est.residual_ns / 1e6,
        "drift_ppm": est.drift_ppm,
        "error_p99_ms": float(np.percentile(error, 99)),
        "error_max_ms": float(error.max()),
    }


class SteppingClock:
    """Virtual time that moves on when the driver waits: 60 s of IMU in a few seconds."""

    def __init__(self) -> None:
        self.t = 0

    def now_ns(self) -> int:
        return self.t

    def sleep_until(self, t_ns: int) -> None:
        self.t = max(self.t, t_ns)


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.degrees(2 * np.arccos(min(1.0, abs(float(np.dot(a, b)))))))


def fusion(seconds: float = 60.0, seed: int = 1) -> dict:
    clock = SteppingClock()
    driver = open_driver(f"hid://stub?device=dk2&seed={seed}", clock)
    driver.open()
    truth = HeadMotion.synthetic(seed)
    errors, frame = [], None
    started = time.perf_counter()
    while clock.t < seconds * 1e9:
        for pose in driver.read(0.05):
            q_true, q = truth.at(pose.t_dev)[0], np.array(pose.orientation)
            if frame is None:  # the filter's world frame: the true pose turned to the yaw it levelled at
                frame = quat_multiply(q, q_true * np.array([1.0, -1.0, -1.0, -1.0]))
            errors.append((pose.t_dev, _angle_deg(q, quat_multiply(frame, q_true))))
    driver.close()
    errors = np.array(errors)
    return {
        "error_at_60s_deg": float(errors[-1, 1]),
        "error_max_last_10s_deg": float(errors[errors[:, 0] > (seconds - 10) * 1e9, 1].max()),
        "error_max_deg": float(errors[:, 1].max()),
        "wall_s": time.perf_counter() - started,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=10.0, help="how long each driver runs (default 10)")
    ap.add_argument("--only", nargs="+", default=["smi", "pupil", "dk2", "razor", "clock", "fusion"])
    args = ap.parse_args()
    only = set(args.only)
    rows = driver_rows(args.seconds, only)
    if rows:
        print(f"{'driver':<18} {'rate Hz':>15} {'samples':>8} {'dropped':>8} {'latency ms p50/p99/max':>24}  from")
        for r in rows:
            print(
                f"{r['driver']:<18} {r['measured_hz']:>7.1f} of {r['expected_hz']:>4.0f} {r['samples']:>8} "
                f"{r['dropped']:>8} {r['p50_ms']:>9.3f} {r['p99_ms']:>6.3f} {r['max_ms']:>6.2f}  {r['from']}"
            )
    if "clock" in only:
        c = clock_sync()
        print(
            f"clock sync (60 s, 250 Hz, 2 ms jitter, 50 ppm): residual {c['residual_ms']:.3f} ms, drift "
            f"{c['drift_ppm']:.1f} ppm, mapping error p99 {c['error_p99_ms']:.3f} ms (max {c['error_max_ms']:.3f})"
        )
    if "fusion" in only:
        f = fusion()
        print(
            f"fusion (hid://stub, 60 s): error after 60 s {f['error_at_60s_deg']:.2f} deg, max over the last 10 s "
            f"{f['error_max_last_10s_deg']:.2f}, max {f['error_max_deg']:.2f} ({f['wall_s']:.1f} s wall)"
        )


if __name__ == "__main__":
    main()
