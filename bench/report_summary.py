"""What one `stats` summary of the run report costs after a minute, ten minutes and an hour at 30 Hz.

    python bench/report_summary.py

The daemon publishes the run report so far each second; the summary is taken (snapshot, then to_dict) with
the GIL held, so its time is time the render and display threads may wait. The report keeps its times in
bounded histograms (hmdrt.telemetry.histogram): the cost should not grow with the run. Prints the best of
five summaries per run length, measured in one run.
"""

from __future__ import annotations

import time

import numpy as np

from hmdrt.telemetry.report import FrameRecord, RunReport, SampleUse

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


def main() -> None:
    print("one summary of the run report (snapshot + to_dict), best of 5")
    for label, seconds in (("1 min", 60), ("10 min", 600), ("1 h", 3600)):
        report = report_of(seconds * 30)
        best = min(_timed(report) for _ in range(5))
        print(f"  {label:>6} at 30 Hz ({seconds * 30:>6} frames): {best * 1e3:6.3f} ms")


def _timed(report: RunReport) -> float:
    t0 = time.perf_counter()
    report.snapshot().to_dict()
    return time.perf_counter() - t0


if __name__ == "__main__":
    main()
