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
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path
from typing import NamedTuple

import msgspec

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from hmdrt.clock import VirtualClock  # noqa: E402
from hmdrt.compositor.clock import VsyncClock  # noqa: E402
from hmdrt.compositor.config import Bus, load_config  # noqa: E402
from hmdrt.compositor.daemon import Compositor  # noqa: E402
from hmdrt.compositor.pacer import Pacer, pacing_settings, replay_frame  # noqa: E402

ANY_PORT = "tcp://127.0.0.1:*"


class Timed(Compositor):
    """The compositor, keeping the work (ns, wake-up to hand-over) of every rendered frame it shows."""

    def __init__(self, *args, **kwargs):
        self.times: list[int] = []
        super().__init__(*args, **kwargs)

    def _shown(self, record, images) -> None:
        if record.shown != "repeat":
            self.times.append(round(record.frame_ms * 1e6))
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
    ages = [
        vsync - wake
        for (present, wake), (following, _) in zip(shown, shown[1:], strict=False)
        for vsync in range(present, following, period_ns)
    ]
    ages.sort()
    p99 = ages[min(len(ages) - 1, math.ceil(0.99 * len(ages)) - 1)] / period_ns
    return Replayed(misses / len(times), lead_ns / len(times) / 1e6, 1 - (len(shown) - 1) / len(ages), p99)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(Path(__file__).resolve().parent.parent / "configs" / "default.toml"))
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--windows", default="30,90,150,300,600")
    args = ap.parse_args()
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
