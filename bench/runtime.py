"""The compositor's numbers in real time: deadline misses, gaze-to-photon latency and compositor
overhead for configs/default.toml (both eyes at sim-cpu-640, 640x720 per eye, 30 Hz); misses with the budget
controller off and on where the method alone cannot hold the rate; and graceful degradation at rift_s, where
nothing can. Each row states the display it ran and the image buffers the run allocated (a pool of a few
per eye; more would mean images copied or kept).

    python bench/runtime.py [--duration 60] [--controller-duration 30] [--only default,controller,rift_s]
                            [--watch [--pairs 3]]

Each scenario runs the daemon in-process on its config with the bus on free loopback ports, for the given
wall time, and prints the run report's figures. These machines are shared: a busy neighbour shows up as
misses, so run it on a quiet machine and read the figures together, as measured in one run.

With --watch the default scenario runs in pairs, once as it is and once watched (in place of its controller-off
run), the order alternating from pair to pair (plain, watched; watched, plain; ...) so that a neighbour's load falls
on both: an `hmdrt watch` process on the compositor and a websocket client of it taking every message, previews
included, as an open page would. It prints each pair's misses after warm-up, the watched runs' extra misses in
points (each pair's difference, their mean and range), the compositor overhead and frame times of the last pair
side by side, and what the previews cost (made on the compositor's preview thread).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import aiohttp
import msgspec

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from hmdrt.compositor.config import Bus, RunConfig, load_config  # noqa: E402
from hmdrt.compositor.daemon import Compositor  # noqa: E402
from hmdrt.evaluate.provenance import machine  # noqa: E402

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ANY_PORT = "tcp://127.0.0.1:*"


class Watcher:
    """`hmdrt watch` on a compositor and a websocket client of its page taking every message, each in a process of
    its own (as a browser would be), so that neither takes the compositor's interpreter lock."""

    def __init__(self, control: str):
        self.server = subprocess.Popen(
            [sys.executable, "-m", "hmdrt", "watch", "--control", control, "--port", "0"],
            stdout=subprocess.PIPE,
            text=True,
        )
        line = self.server.stdout.readline()
        found = re.search(r"\(read-only: (http://\S+)\)", line)
        if not found:
            self.server.kill()
            raise SystemExit(f"hmdrt watch did not start: {line!r}")
        self._started_cpu_s = self._server_cpu_s()  # its start-up (imports) is not the watching
        self.client = subprocess.Popen(
            [sys.executable, __file__, "--watch-client", found[1] + "ws"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )

    def close(self) -> dict:
        """Stop both; what the client took (previews, their bytes, other messages) and the server's CPU seconds."""
        counts, _ = self.client.communicate("", timeout=30)  # its stdin closed: it stops and prints its counts
        cpu_s = self._server_cpu_s() - self._started_cpu_s
        self.server.terminate()
        self.server.wait(10)
        return {**json.loads(counts), "server_cpu_s": cpu_s}

    def _server_cpu_s(self) -> float:
        """The watch process's CPU seconds so far: utime + stime of /proc/PID/stat (proc(5))."""
        fields = Path(f"/proc/{self.server.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def take_messages(url: str) -> dict:
    """Take every message of a watch page's websocket until stdin closes; the counts (Watcher's client)."""
    counts = {"previews": 0, "preview_bytes": 0, "messages": 0}
    closed = asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)
    async with aiohttp.ClientSession() as session, session.ws_connect(url) as ws:
        while not closed.done():
            receiving = asyncio.ensure_future(ws.receive())
            await asyncio.wait({receiving, closed}, return_when=asyncio.FIRST_COMPLETED)
            if not receiving.done():
                receiving.cancel()
                break
            message = receiving.result()
            if message.type == aiohttp.WSMsgType.BINARY:
                counts["previews"] += 1
                counts["preview_bytes"] += len(message.data)
            elif message.type == aiohttp.WSMsgType.TEXT:
                counts["messages"] += 1
            else:
                break
    return counts


def run(config: RunConfig, watched: bool = False) -> dict:
    """The run report of a config; watched: with a Watcher, and its figures under "watch"."""
    config = msgspec.structs.replace(config, bus=Bus(ANY_PORT, ANY_PORT, ANY_PORT))
    compositor = Compositor(config)
    try:
        if not watched:
            return compositor.run()
        watcher = Watcher(compositor.control.address)
        try:
            report = compositor.run()
        finally:
            taken = watcher.close()
        preview = compositor.preview
        report["watch"] = {
            "previews_received": taken["previews"],
            "preview_kb": taken["preview_bytes"] / 1024,
            "messages_received": taken["messages"],
            "previews_made": preview.sent,
            "replaced": preview.replaced,
            "preview_ms": 1e3 * preview.busy_s / max(preview.sent, 1),
            "preview_thread_share": preview.busy_s / config.run.duration_s,
            "server_share": taken["server_cpu_s"] / config.run.duration_s,
        }
        return report
    finally:
        compositor.close()


def compare_watched(plain: dict, watched: dict) -> None:
    """The compositor's overhead and frame times without and with a watcher, and what the previews cost."""
    w = watched["watch"]
    rows = {
        "compositor overhead ms": lambda r: r["compositor_overhead_ms"],
        "frame ms": lambda r: r["frame_ms"],
        "gaze-to-photon ms": lambda r: r["latency_ms"]["gaze_to_photon"],
    }
    for label, of in rows.items():
        a, b = of(plain), of(watched)
        print(f"  {label}: p50 {a['p50']} -> {b['p50']}, p99 {a['p99']} -> {b['p99']} (without -> with a watcher)")
    print(
        f"  misses after warm-up {plain['miss_rate_after_warmup']:.2%} -> {watched['miss_rate_after_warmup']:.2%}, "
        f"achieved {plain['achieved_hz']:g} -> {watched['achieved_hz']:g} Hz"
    )
    print(
        f"  watcher: {w['previews_received']} previews received ({w['preview_kb']:.0f} KiB), "
        f"{w['messages_received']} other messages; the compositor made {w['previews_made']} previews "
        f"({w['replaced']} replaced before encoding) at {w['preview_ms']:.2f} ms each on its preview thread "
        f"({w['preview_thread_share']:.1%} of one core's wall time); the hmdrt watch process used "
        f"{w['server_share']:.1%} of a core after its start"
    )


def watch_pairs(config: RunConfig, pairs: int) -> None:
    """The misses a watcher adds, from pairs of runs in alternating order, each pair's difference in points."""
    added, last = [], None
    for k in range(pairs):
        order = (False, True) if k % 2 == 0 else (True, False)
        reports = {watched: run(config, watched=watched) for watched in order}
        plain, watched = reports[False], reports[True]
        added.append(100 * (watched["miss_rate_after_warmup"] - plain["miss_rate_after_warmup"]))
        print(
            f"  pair {k + 1} ({'plain first' if k % 2 == 0 else 'watched first'}): misses after warm-up "
            f"{plain['miss_rate_after_warmup']:.2%} -> {watched['miss_rate_after_warmup']:.2%} watched "
            f"({added[-1]:+.2f} points); gaze-to-photon p99 {periods(plain):.2f} -> {periods(watched):.2f} periods"
        )
        last = plain, watched
    print(
        f"  a watcher adds {sum(added) / len(added):+.2f} points of misses after warm-up, mean of {len(added)} "
        f"pairs (range {min(added):+.2f} to {max(added):+.2f})"
    )
    describe("default (last pair)", last[0])
    describe("default, watched (last pair)", last[1])
    compare_watched(*last)


def periods(report: dict) -> float:
    """Gaze-to-photon p99 in VSync periods."""
    return (report["latency_ms"]["gaze_to_photon"]["p99"] or 0) * report["vsync_hz"] / 1e3


def with_controller(config: RunConfig, kind: str) -> RunConfig:
    return msgspec.structs.replace(config, controller=msgspec.structs.replace(config.controller, kind=kind))


def describe(name: str, report: dict) -> None:
    gaze, overhead = report["latency_ms"]["gaze_to_photon"], report["compositor_overhead_ms"]
    d, buffers = report["display"], report["image_buffers"]
    print(
        f"  {name}: {report['method_spec']} at {d['profile']} {d['width']}x{d['height']} x {len(d['eyes'])} eyes "
        f"{d['refresh_hz']:g} Hz, {report['vsyncs']} VSyncs, achieved {report['achieved_hz']:g} Hz, "
        f"out of order {report['out_of_order']}"
    )
    print(
        f"    misses {report['deadline_misses']} = {report['miss_rate']:.2%} "
        f"(after {report['warmup_s']:g} s warm-up {report['miss_rate_after_warmup']:.2%}); "
        f"shown {report['presented']} ({report['late']} late), dropped {report['dropped']}, "
        f"repeated {report['re_presented']} = {report['repeat_rate']:.1%} of VSyncs"
    )
    print(
        f"    frame ms p50 {report['frame_ms']['p50']} p99 {report['frame_ms']['p99']}; "
        f"gaze-to-photon ms p50 {gaze['p50']} p99 {gaze['p99']} = {periods(report):.2f} periods; "
        f"compositor overhead ms p50 {overhead['p50']} p99 {overhead['p99']}; "
        f"timewarp ms p50 {report['timewarp_ms']['p50']}, skipped {report['timewarp_skipped']}"
    )
    print(
        f"    image buffers allocated over the run: rendered {buffers['rendered']['allocated']}, "
        f"warped {buffers['warped']['allocated']}"
    )
    controller = report.get("controller")
    if controller:
        levels = [step["level"] for step in controller["trajectory"]]
        print(
            f"    controller: {controller['changes']} changes, level {levels[0] if levels else 1.0} -> "
            f"{controller['level']}, at floor {controller['at_floor']}; "
            f"last knobs {controller['trajectory'][-1] if levels else {}}"
        )
        spread = report["controller_level"]
        if spread:
            print(
                f"    level over the {spread['frames']} new frames: p10 {spread['p10']} p50 {spread['p50']} "
                f"p90 {spread['p90']}, at 0.5 or above {spread['share_at_least_half']:.1%} of them"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds for configs/default.toml")
    ap.add_argument("--controller-duration", type=float, default=30.0, help="seconds per controller run")
    ap.add_argument("--only", default="default,controller,rift_s")
    ap.add_argument("--watch", action="store_true", help="the default scenario in pairs, plain and watched")
    ap.add_argument("--pairs", type=int, default=3, help="--watch's pairs of runs")
    ap.add_argument("--watch-client", metavar="URL", help=argparse.SUPPRESS)  # Watcher's client process
    args = ap.parse_args()
    if args.watch_client:
        print(json.dumps(asyncio.run(take_messages(args.watch_client))))
        return
    only = set(args.only.split(","))
    print(machine())

    if "default" in only:
        print(f"configs/default.toml, {args.duration:g} s real time")
        config = load_config(CONFIGS / "default.toml", duration_s=args.duration)
        if args.watch:
            watch_pairs(config, args.pairs)
        else:
            describe("default", run(config))
            describe("default, controller off", run(with_controller(config, "none")))
    if "controller" in only:
        config = load_config(CONFIGS / "bench" / "controller.toml", duration_s=args.controller_duration)
        print(f"configs/bench/controller.toml, {args.controller_duration:g} s real time each")
        off, on = (run(with_controller(config, kind)) for kind in ("none", "hold-budget"))
        describe("controller off", off)
        describe("controller on", on)
        print(
            f"  misses after warm-up: off {off['miss_rate_after_warmup']:.2%}, on {on['miss_rate_after_warmup']:.2%}; "
            f"VSyncs without a new frame: off {off['repeat_rate']:.1%}, on {on['repeat_rate']:.1%}; "
            f"achieved {off['achieved_hz']:g} -> {on['achieved_hz']:g} of {on['vsync_hz']:g} Hz"
        )
    if "rift_s" in only:
        config = load_config(CONFIGS / "bench" / "rift_s.toml", duration_s=args.controller_duration)
        print(f"configs/bench/rift_s.toml, {args.controller_duration:g} s real time")
        describe("rift_s", run(config))


if __name__ == "__main__":
    main()
