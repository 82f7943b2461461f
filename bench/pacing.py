"""What the pacer's tail window does to misses and latency, on render times measured in one real-time run.

    python bench/pacing.py [--config configs/default.toml] [--duration 60] [--windows 30,90,150,300,600]

Runs the config in real time for --duration seconds (bus on free loopback ports), keeps each shown frame's
work from wake-up to hand-over, then replays those times in order through the pacer on a virtual clock: once
per tail_window, and once on the filtered mean alone (Monado's plan). It prints the misses each would have
had, how long before its VSync a frame woke on average (what the plan costs in latency), the VSyncs that showed
no new frame (a late frame's, and those a two-period interval leaves) and the p99 over VSyncs of the time from the
shown frame's wake-up to its VSync, in periods: gaze-to-photon less the gaze sample's age, which is what holds
the run report's gaze-to-photon p99. Every row sees the same times, so the comparison does not depend on how busy
the machine was. Planning for the largest of the last W times, a frame exceeds the plan about once in W + 1 frames
when render times are independent; the margin catches some of those.

    python bench/pacing.py --controller [--frames 1860] [--scales 0.9,1.0,1.1,1.2] [--jitter 0.1] [--seeds 3]
                           [--plant FILE]

With --controller it judges the budget controller with the pacer instead, on frames whose cost depends on the
controller's level: it renders the config's first --frames frames in virtual time (the same gaze, frame by frame)
with the method's knobs at levels 0, 0.5 and 1, the controller off, keeping each frame's work, rays and what the
foresight probe reads of its fovea (hmdrt.compositor.foresight, and how long it took), then replays the config's
pacer and controller on a virtual clock, frame k at level L costing its work interpolated between those levels
(plus the probe's, where the controller foresees), times a scale (a real-time run renders the same frames 1.15-1.2x
slower than a virtual-time one on these machines, docs/performance.md, "Goal 4 on the EPYC") and a log-normal
jitter of --jitter (one seeded draw per frame). For each scale and control law (feedback alone, and foresight where
the method has a foveal knob) it prints goal 4's figures: misses, the p99 over VSyncs of the shown frame's wake-up
to its VSync plus a 250 Hz sample's mean age (the gaze-to-photon p99), and the share of frames at level 0.5 or
above. Every row sees the same frames, so a control law is judged apart from the machine's noise; with --plant the
measured frames are written to FILE, or read from it when it exists, so that two versions of the controller can be
replayed on the very same frames.
"""

from __future__ import annotations

import argparse
import math
import random
import sys
import time
from pathlib import Path
from typing import NamedTuple

import msgspec

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from hmdrt.clock import VirtualClock  # noqa: E402
from hmdrt.compositor.clock import VsyncClock  # noqa: E402
from hmdrt.compositor.config import Bus, RunConfig, load_config  # noqa: E402
from hmdrt.compositor.controller import make_controller, spans  # noqa: E402
from hmdrt.compositor.daemon import Compositor  # noqa: E402
from hmdrt.compositor.foresight import Foresight, FovealProbe  # noqa: E402
from hmdrt.compositor.pacer import Pacer, pacing_settings, replay_frame  # noqa: E402
from hmdrt.foveation import METHODS  # noqa: E402
from hmdrt.scene import load_scene  # noqa: E402
from hmdrt.trace.integrator import Whitted  # noqa: E402

ANY_PORT = "tcp://127.0.0.1:*"
LEVELS = (0.0, 0.5, 1.0)  # the controller's levels the plant is measured at
SAMPLE_AGE_MS = 2.0  # a gaze sample's mean age at wake-up: half the default trace's 4 ms interval (250 Hz)


class Timed(Compositor):
    """The compositor, keeping the work (ns, wake-up to hand-over) and rays of every rendered frame it shows."""

    def __init__(self, *args, **kwargs):
        self.times: list[int] = []
        self.rays: list[int] = []
        super().__init__(*args, **kwargs)

    def _shown(self, record, images) -> None:
        if record.shown != "repeat":
            self.times.append(round(record.frame_ms * 1e6))
            self.rays.append(record.rays)
        super()._shown(record, images)


class Probed(Timed):
    """Timed, also reading the foresight probe of each frame's fovea at `radius_deg` after the frame is built (its
    time apart from the frame's work): each shown frame's reading and the probe's time (ns)."""

    def __init__(self, config: RunConfig, radius_deg: float):
        super().__init__(config)
        self.fores: list[Foresight] = []
        self.probe_ns: list[int] = []
        self._read: dict[int, tuple[Foresight, int]] = {}
        probe, build = FovealProbe(self.session.tracer), self.builder.build

        def probed(timing, woke, loop_ns=0):
            frame = build(timing, woke, loop_ns)
            start = time.perf_counter_ns()
            directions = frame.gaze_dirs or self.session.directions(None)[0]
            fore = probe.read(frame.cameras, directions, radius_deg)
            self._read[timing.frame_id] = (fore, time.perf_counter_ns() - start)
            return frame

        self.builder.build = probed

    def _shown(self, record, images) -> None:
        if record.shown != "repeat":
            fore, took = self._read.pop(record.frame_id)
            self.fores.append(fore)
            self.probe_ns.append(took)
        super()._shown(record, images)


def measure(config_path: str, duration_s: float) -> tuple[list[int], int, dict]:
    """Render times (ns, wake-up to hand-over) of the frames a real-time run showed, its period and pacer settings."""
    config = load_config(config_path)
    config = msgspec.structs.replace(
        config, bus=Bus(ANY_PORT, ANY_PORT, ANY_PORT), run=msgspec.structs.replace(config.run, duration_s=duration_s)
    )
    compositor = Timed(config)
    try:
        report = compositor.run()
        settings = pacing_settings(config.pacing, compositor.vsync.period_ns)
        times = compositor.times
        period = compositor.vsync.period_ns
    finally:
        compositor.close()
    print(
        f"{config_path}: {len(times)} frames in {duration_s:g} s real time, misses {report['miss_rate']:.2%} "
        f"(tail_window {settings['tail_window']}), frame ms p50 {report['frame_ms']['p50']} "
        f"p99 {report['frame_ms']['p99']}"
    )
    return times, period, settings


class Replayed(NamedTuple):
    """What the pacer with some settings made of one run's render times."""

    miss_rate: float
    lead_ms: float  # mean time from wake-up to desired present
    repeat_rate: float  # VSyncs without a new frame
    p99_periods: float  # wake-up of the frame shown to its VSync, p99 over VSyncs


def replay(times: list[int], period_ns: int, settings: dict) -> Replayed:
    """The pacer with these settings on these times: each frame shown from its actual present until the next one's,
    as the display does."""
    pacer = Pacer(VsyncClock(period_ns, 0), **settings)
    clock = VirtualClock(0)
    misses, lead_ns, shown = 0, 0, []
    for render_ns in times:
        timing, present, missed = replay_frame(pacer, clock, render_ns)
        misses += missed
        lead_ns += timing.desired_present_ns - timing.wake_ns
        shown.append((present, timing.wake_ns))
    ages = _ages(shown, period_ns)
    p99 = _p99(ages) / period_ns
    return Replayed(misses / len(times), lead_ns / len(times) / 1e6, 1 - (len(shown) - 1) / len(ages), p99)


def _ages(shown: list[tuple[int, int]], period_ns: int) -> list[int]:
    """For every VSync, how long before it the frame it showed woke: each (present, wake) shown until the next."""
    return [
        vsync - wake
        for (present, wake), (following, _) in zip(shown, shown[1:], strict=False)
        for vsync in range(present, following, period_ns)
    ]


def _p99(values: list) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, math.ceil(0.99 * len(ordered)) - 1)]


class Plant(msgspec.Struct, frozen=True):
    """The frames plant() measured, per level and frame: work (ns), rays, the probe's reading of the fovea and the
    probe's time (ns); and the display's period."""

    levels: tuple[float, ...]
    times: list[list[int]]
    rays: list[list[int]]
    fores: list[list[Foresight]]
    probe_ns: list[list[int]]
    period_ns: int


def plant(config: RunConfig, frames: int) -> Plant:
    """Each frame in virtual time with the method's knobs at each of LEVELS, the controller off."""
    choice = config.method_choice
    method = METHODS[choice.name]
    knobs = spans(method, choice.params)
    if not knobs:
        raise SystemExit(f"{choice.name} has no cost knobs: the controller has nothing to replay")
    foveal = next((k for k in knobs if k.foveal), None)
    runs = []
    for level in LEVELS:
        options = {**config.method.options, **{k.field: k.at(level, 0.0) for k in knobs}}
        run = msgspec.structs.replace(config.run, virtual_time=True, frames=frames, duration_s=0.0)
        at = msgspec.structs.replace(
            config,
            bus=Bus(ANY_PORT, ANY_PORT, ANY_PORT),
            method=msgspec.structs.replace(config.method, options=options),
            controller=msgspec.structs.replace(config.controller, kind="none"),
            run=run,
        )
        compositor = Probed(at, foveal.at(level, 0.0) if foveal else 0.0)
        try:
            compositor.run()
            runs.append(compositor)
        finally:
            compositor.close()
        times = compositor.times
        print(
            f"  level {level:g} ({', '.join(f'{k}={v:g}' for k, v in options.items())}): "
            f"work p50 {sorted(times)[len(times) // 2] / 1e6:.1f} ms, p99 {_p99(times) / 1e6:.1f} ms; "
            f"the probe p50 {sorted(compositor.probe_ns)[len(times) // 2] / 1e6:.2f} ms"
        )
    n = min(len(c.times) for c in runs)
    return Plant(
        LEVELS,
        [c.times[:n] for c in runs],
        [c.rays[:n] for c in runs],
        [c.fores[:n] for c in runs],
        [c.probe_ns[:n] for c in runs],
        runs[0].vsync.period_ns,
    )


def cost(times: list[list[float]], k: int, level: float) -> float:
    """Frame k's work (or another figure) at `level`, interpolated between the two measured levels around it."""
    upper = min(max(1, next(i for i, at in enumerate(LEVELS) if at >= level)), len(LEVELS) - 1)
    lo, hi = LEVELS[upper - 1], LEVELS[upper]
    w = (level - lo) / (hi - lo)
    return (1 - w) * times[upper - 1][k] + w * times[upper][k]


def load_plant(config: RunConfig, frames: int, path: str) -> Plant:
    """plant()'s frames, read from `path` when it exists, else measured and written there ("": not kept)."""
    if path and Path(path).exists():
        try:
            kept = msgspec.json.decode(Path(path).read_bytes(), type=Plant)
        except msgspec.DecodeError as exc:  # malformed JSON too (ValidationError is one)
            raise SystemExit(f"{path}: not a plant this bench wrote: {exc}") from None
        if kept.levels != LEVELS or len({len(t) for t in kept.times}) != 1:
            raise SystemExit(f"{path}: measured at levels {kept.levels}, this bench replays {LEVELS}")
        print(f"  the plant of {path}: {len(kept.times[0])} frames")
        return kept
    measured = plant(config, frames)
    if path:
        Path(path).write_bytes(msgspec.json.encode(measured))
    return measured


class Controlled(NamedTuple):
    """What the pacer and the controller made of the plant at one scale."""

    misses: int
    frames: int
    p99_periods: float  # gaze-to-photon p99 over VSyncs: wake-up to VSync plus a sample's mean age
    level_share: float  # frames at level 0.5 or above


def replay_controller(
    config: RunConfig, tracer: Whitted, measured: Plant, scale: float, jitter: float, seed: int
) -> Controlled:
    """The config's pacer and controller on the plant: the frame planned when the one before ended is frame k of
    the plant at that time, at the level the controller then holds (a foresighted one picks it from the probe's
    reading, interpolated at the level it holds); the controller learns of each frame when it is presented, before
    the next is planned."""
    vsync = VsyncClock(measured.period_ns, 0)
    settings = pacing_settings(config.pacing, vsync.period_ns)
    pacer, clock, rng = Pacer(vsync, **settings), VirtualClock(0), random.Random(seed)
    controller = make_controller(config, config.method_choice.make(tracer))
    if controller is None:
        raise SystemExit(f"{config.source}: [controller] kind is none: there is no controller to replay")
    budget = vsync.period_ns - pacer.margin_ns
    times, rays = measured.times, measured.rays
    rays_per_pixel = [[f.rays_per_pixel for f in level] for level in measured.fores]
    pixels = [[f.pixels for f in level] for level in measured.fores]
    shown, levels, misses = [], [], 0
    while (k := round(clock.now_ns() / vsync.period_ns)) < len(times[0]):
        frame_id, work = len(shown), 0.0
        if controller.foresees:
            level = controller.level
            read = Foresight(cost(rays_per_pixel, k, level), round(cost(pixels, k, level)), controller.fovea_deg)
            controller.anticipate(frame_id, read)
            work = cost(measured.probe_ns, k, level)
        level = controller.level
        work = round((work + cost(times, k, level)) * scale * rng.lognormvariate(0.0, jitter))
        timing, present, missed = replay_frame(pacer, clock, work)
        controller.update(frame_id, work, budget, missed, rays=round(cost(rays, k, level)))
        misses += missed
        shown.append((present, timing.wake_ns))
        levels.append(level)
    p99 = (_p99(_ages(shown, vsync.period_ns)) / 1e6 + SAMPLE_AGE_MS) / (vsync.period_ns / 1e6)
    return Controlled(misses, len(shown), p99, sum(at >= 0.5 for at in levels) / len(levels))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(Path(__file__).resolve().parent.parent / "configs" / "default.toml"))
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--windows", default="30,90,150,300,600")
    ap.add_argument("--controller", action="store_true", help="replay the budget controller on a measured plant")
    ap.add_argument("--frames", type=int, default=1860)
    ap.add_argument("--scales", default="0.9,1.0,1.1,1.2")
    ap.add_argument("--jitter", type=float, default=0.1)
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--plant", default="", help="keep the measured frames in this file, or read them from it")
    args = ap.parse_args()
    if args.controller:
        config = load_config(args.config)
        print(f"{args.config}: {config.method.name} on {config.scene}, {args.frames} frames in virtual time per level")
        measured = load_plant(config, args.frames, args.plant)
        print(
            f"replayed through the pacer and the {config.controller.kind} controller, jitter {args.jitter:g}, "
            f"{args.seeds} seeds (misses, gaze-to-photon p99 in periods, frames at level >= 0.5):"
        )
        laws = {
            law: msgspec.structs.replace(config, controller=msgspec.structs.replace(config.controller, foresight=law))
            for law in (False, True)
        }
        with Whitted(load_scene(config.scene)) as tracer:
            if not make_controller(laws[True], config.method_choice.make(tracer)).foresees:
                del laws[True]
            for scale in (float(x) for x in args.scales.split(",")):
                for law, at in laws.items():
                    rows = [replay_controller(at, tracer, measured, scale, args.jitter, s) for s in range(args.seeds)]
                    print(
                        f"  work x{scale:<4g} {'foresight' if law else 'feedback':9s}  "
                        + "   ".join(
                            f"{r.misses:3d} of {r.frames} ({r.misses / r.frames:.2%}), p99 {r.p99_periods:.2f}, "
                            f"level {r.level_share:.0%}"
                            for r in rows
                        )
                    )
        return
    times, period, settings = measure(args.config, args.duration)
    print(f"replayed through the pacer (margin {settings['margin_ns'] / 1e6:g} ms, period {period / 1e6:.2f} ms):")
    rows = [("filtered mean only", {**settings, "tail_quantile": None})]
    rows += [(f"tail_window {w}", {**settings, "tail_window": int(w)}) for w in args.windows.split(",")]
    for name, row in rows:
        r = replay(times, period, row)
        print(
            f"  {name:20s} misses {r.miss_rate:6.2%}   wake-up {r.lead_ms:5.1f} ms before its VSync   "
            f"repeats {r.repeat_rate:6.2%}   wake-up to VSync p99 {r.p99_periods:.2f} periods"
        )


if __name__ == "__main__":
    main()
