"""What an hours-long run costs the frames, now and then: the `stats` summary of the run report each second,
after a minute, ten minutes and an hour at 30 Hz, and a full garbage collection once the compositor has
started, with its start-up heap frozen (as the compositor does) and not.

    python bench/long_run.py

Both hold the GIL: their time is time the render and display threads may wait. The report keeps its times
in bounded histograms (hmdrt.telemetry.histogram), so a summary should cost the same at any length; the
compositor freezes what start-up built (gc.freeze) so that a collection during the run does not scan it.
Prints the best of five of each, measured in one run.
"""

from __future__ import annotations

import gc
import sys
import time
from pathlib import Path

import msgspec
import numpy as np

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from hmdrt.compositor.config import Bus, load_config  # noqa: E402
from hmdrt.compositor.daemon import Compositor  # noqa: E402
from hmdrt.telemetry.report import FrameRecord, RunReport, SampleUse  # noqa: E402

PERIOD_NS = 33_333_333


def report_of(frames: int, seed: int = 0) -> RunReport:
    """A report of `frames` new frames with render times like the default config's (median ~10 ms)."""
    rng = np.random.default_rng(seed)
    report, t = RunReport(30.0), 0
    for i, render_ms in enumerate(rng.lognormal(2.3, 0.3, frames)):
        t += PERIOD_NS
        sample = SampleUse("trk", i, t - 30_000_000)
        report.add(
            FrameRecord(
                vsync=i,
                frame_id=i,
                shown="new",
                actual_present_ns=t,
                predicted_wake_ns=t - 20_000_000,
                predicted_present_ns=t,
                predicted_display_ns=t + PERIOD_NS // 2,
                actual_wake_ns=t - 20_000_000,
                render_start_ns=t - 19_500_000,
                render_end_ns=t - 5_000_000,
                missed=False,
                gaze=sample,
                pose=sample,
                frame_ms=float(render_ms) + 0.5,
                render_ms=float(render_ms),
                present_ms=0.05,
            )
        )
    return report


def best_of(work, times: int = 5) -> float:
    """Best wall milliseconds of `times` calls."""
    best = float("inf")
    for _ in range(times):
        t0 = time.perf_counter()
        work()
        best = min(best, time.perf_counter() - t0)
    return best * 1e3


def main() -> None:
    print("one summary of the run report (snapshot + to_dict), best of 5")
    for label, seconds in (("1 min", 60), ("10 min", 600), ("1 h", 3600)):
        report = report_of(seconds * 30)
        summary = best_of(lambda r=report: r.snapshot().to_dict())
        print(f"  {label:>6} at 30 Hz ({seconds * 30:>6} frames): {summary:6.3f} ms")
    config = load_config(Path(__file__).resolve().parent.parent / "configs" / "default.toml")
    any_port = "tcp://127.0.0.1:*"
    compositor = Compositor(msgspec.structs.replace(config, bus=Bus(any_port, any_port)))
    try:
        frozen, objects = best_of(gc.collect), gc.get_freeze_count()
        gc.unfreeze()
        print(f"a full collection after the default config's start-up ({objects} objects frozen), best of 5")
        print(f"  frozen {frozen:.3f} ms, not frozen {best_of(gc.collect):.1f} ms")
    finally:
        compositor.close()


if __name__ == "__main__":
    main()
