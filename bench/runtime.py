"""The compositor's numbers in real time (issue 5): deadline misses, gaze-to-photon latency and compositor
overhead for configs/default.toml (both eyes at sim-cpu-640, 640x720 per eye, 30 Hz); misses with the budget
controller off and on where the method alone cannot hold the rate; and graceful degradation at rift_s, where
nothing can. Each row states the display it ran and the image buffers the run allocated (a pool of a few
per eye; more would mean images copied or kept).

    python bench/runtime.py [--duration 60] [--controller-duration 30] [--only default,controller,rift_s]

Each scenario runs the daemon in-process on its config with the bus on free loopback ports, for the given
wall time, and prints the run report's figures. These machines are shared: a busy neighbour shows up as
misses, so run it on a quiet machine and read the figures together, as measured in one run.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import msgspec

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from hmdrt.compositor.config import Bus, RunConfig, load_config  # noqa: E402
from hmdrt.compositor.daemon import Compositor  # noqa: E402

CONFIGS = Path(__file__).resolve().parent.parent / "configs"
ANY_PORT = "tcp://127.0.0.1:*"


def run(config: RunConfig) -> dict:
    config = msgspec.structs.replace(config, bus=Bus(ANY_PORT, ANY_PORT, ANY_PORT))
    compositor = Compositor(config)
    try:
        return compositor.run()
    finally:
        compositor.close()


def with_controller(config: RunConfig, kind: str) -> RunConfig:
    return msgspec.structs.replace(config, controller=msgspec.structs.replace(config.controller, kind=kind))


def describe(name: str, report: dict) -> None:
    period_ms = 1e3 / report["vsync_hz"]
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
        f"gaze-to-photon ms p50 {gaze['p50']} p99 {gaze['p99']} = {(gaze['p99'] or 0) / period_ms:.2f} periods; "
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="seconds for configs/default.toml")
    ap.add_argument("--controller-duration", type=float, default=30.0, help="seconds per controller run")
    ap.add_argument("--only", default="default,controller,rift_s")
    args = ap.parse_args()
    only = set(args.only.split(","))

    if "default" in only:
        print(f"configs/default.toml, {args.duration:g} s real time")
        config = load_config(CONFIGS / "default.toml", duration_s=args.duration)
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
