"""What a control flood costs the compositor: its CPU share and frame rate while another process sends `stats`
requests to its control socket as fast as they go, against the same without, interleaved in one run.

    python bench/control_flood.py [--config configs/default.toml] [--rounds 3] [--phase 5] [--clients 1]

The daemon runs in-process on the config with its control socket on a free loopback tcp:// port (any local user's,
the case the budget is for; hmdrt.bus.limits.CONTROL); its other sockets stay the private defaults. Each round
has a quiet phase and a flood phase of --phase seconds: in the flood, --clients processes each keep up to 2,000
`stats` requests outstanding on a DEALER. A phase measures this process's CPU seconds over its wall time (the
daemon's threads; the clients are processes of their own) and the new frames shown a second. It prints each phase,
then flood over quiet for both, the means over the rounds. These machines are shared: read the ratio, measured in
one run, rather than the absolute figures.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import zmq

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from hmdrt.bus import limits  # noqa: E402
from hmdrt.compositor.config import load_config  # noqa: E402
from hmdrt.compositor.daemon import Compositor  # noqa: E402

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ANY_PORT = "tcp://127.0.0.1:*"
OUTSTANDING = 2000  # requests a client keeps unanswered at most
STATS = msgspec.msgpack.encode({"cmd": "stats"})


def flood(endpoint: str, seconds: float) -> dict:
    """As a client process: stats requests on a DEALER as fast as they go for `seconds`; what came back."""
    context = zmq.Context()
    sock = context.socket(zmq.DEALER)
    sock.setsockopt(zmq.LINGER, 0)
    sock.connect(endpoint)
    print("ready", flush=True)
    sent, replies, limited = 0, 0, 0
    started = time.monotonic()
    while time.monotonic() - started < seconds:
        while sent - replies < OUTSTANDING and sock.poll(0, zmq.POLLOUT):
            sock.send_multipart([b"", STATS], zmq.NOBLOCK)
            sent += 1
        while sock.poll(1):
            reply = msgspec.msgpack.decode(sock.recv_multipart()[-1])
            replies += 1
            limited += not reply.get("ok") and str(reply.get("error", "")).startswith("rate limited")
    context.destroy(linger=0)
    return {"sent": sent, "replies": replies, "limited": limited}


class Phase:
    """One phase's measures: this process's CPU seconds and the new frames shown, over the wall time."""

    def __init__(self, comp: Compositor):
        self.comp = comp
        self.cpu, self.wall, self.frames = time.process_time(), time.monotonic(), self._frames()

    def _frames(self) -> int:
        with self.comp.lock:
            shown = dict(self.comp.report.shown)
        return shown["new"] + shown["late"]

    def end(self) -> dict:
        wall = time.monotonic() - self.wall
        return {
            "cpu_share": (time.process_time() - self.cpu) / wall,
            "fps": (self._frames() - self.frames) / wall,
        }


def run_phase(comp: Compositor, seconds: float, clients: int) -> dict:
    """A phase of `seconds`, quiet (clients 0) or with `clients` flooding processes."""
    procs = [
        subprocess.Popen(
            [sys.executable, __file__, "--flood-client", comp.control.address, "--phase", str(seconds)],
            stdout=subprocess.PIPE,
            text=True,
        )
        for _ in range(clients)
    ]
    for proc in procs:  # their start-up (imports) is not the flood
        if proc.stdout.readline().strip() != "ready":
            raise SystemExit("a flood client did not start")
    phase = Phase(comp)
    time.sleep(seconds)
    measured = phase.end()
    for key in ("sent", "replies", "limited"):
        measured[key] = 0
    for proc in procs:
        out, _ = proc.communicate(timeout=30)
        for key, value in json.loads(out).items():
            measured[key] += value
    return measured


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(CONFIGS / "default.toml"))
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--phase", type=float, default=5.0, help="seconds of each quiet and each flood phase")
    ap.add_argument("--clients", type=int, default=1, help="flooding processes in a flood phase")
    ap.add_argument("--flood-client", metavar="ENDPOINT", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.flood_client:
        print(json.dumps(flood(args.flood_client, args.phase)), flush=True)
        return

    config = load_config(args.config)
    bus = msgspec.structs.replace(config.bus, control=ANY_PORT)
    run = msgspec.structs.replace(config.run, duration_s=0.0, frames=0)
    comp = Compositor(msgspec.structs.replace(config, bus=bus, run=run))
    thread = threading.Thread(target=comp.run, name="compositor")
    thread.start()
    budget = limits.CONTROL
    print(
        f"control flood on {args.config}: {comp.session.spec} at {comp.session.profile.name} "
        f"({comp.session.profile.refresh_hz:g} Hz), control {comp.control.address}; budget {budget.per_peer_hz:g} "
        f"requests/s per peer ({budget.burst:g} at once), {budget.socket_hz:g}/s per socket"
    )
    quiet, flooded = [], []
    try:
        time.sleep(2.0)  # past the first frames
        for n in range(1, args.rounds + 1):
            for label, clients, into in (("quiet", 0, quiet), ("flood", args.clients, flooded)):
                m = run_phase(comp, args.phase, clients)
                into.append(m)
                extra = (
                    f"; {m['sent']} requests sent, {m['replies'] - m['limited']} served, {m['limited']} rate limited"
                    if clients
                    else ""
                )
                print(f"  round {n} {label}: daemon {m['cpu_share']:.1%} of a core, {m['fps']:.1f} new frames/s{extra}")
    finally:
        comp.stop.set()
        thread.join()
        report = comp.summary()
        comp.close()

    def mean(phases: list[dict], key: str) -> float:
        return sum(p[key] for p in phases) / len(phases)

    cpu = mean(flooded, "cpu_share") / max(mean(quiet, "cpu_share"), 1e-9)
    fps = mean(flooded, "fps") / max(mean(quiet, "fps"), 1e-9)
    print(
        f"  flood / quiet over {args.rounds} rounds: CPU share x{cpu:.3f}, frame rate x{fps:.3f}; "
        f"rate limited in the report: {report['rate_limited']['control']}"
    )


if __name__ == "__main__":
    main()
