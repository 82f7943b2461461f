"""The gaze error at photon time: how far each eye was, when a shown frame was seen, from the gaze the frame was
rendered for. Runs in virtual time replay traces whose gaze is known at every instant, so the error each VSync
must show is worked out from its record: a constant-velocity pursuit rendered without prediction lags by the
velocity times the time from the gaze sample used to the photon time; a gaze step is seen at its full size until
a frame rendered after it is shown. The sink is also driven directly, with a sample store and a clock of the
test's own, for what a run does not reach: a full queue, a tracker that never answers, a method without a fovea.
"""

from __future__ import annotations

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from hmdrt.api import run_compositor
from hmdrt.bus.messages import Gaze
from hmdrt.compositor.gaze_error import KEY, MOST_PER_VSYNC, GazeErrors
from hmdrt.compositor.samples import SampleStore
from hmdrt.compositor.sinks import Shown
from hmdrt.telemetry.frames_log import read_frames_log
from hmdrt.telemetry.report import FrameRecord
from hmdrt.testing import assert_gaze_error_within, write_config

from .helpers import gaze_trace

SAMPLE_NS = 4_000_000  # the traces' 250 Hz
FRAMES = 30


def direction(degrees: float) -> tuple[float, float, float]:
    """Unit gaze turned `degrees` to the right of straight ahead (-z), about the head's y axis."""
    a = math.radians(degrees)
    return (math.sin(a), 0.0, -math.cos(a))


def photon_ns(record: FrameRecord) -> int:
    return record.actual_present_ns + record.predicted_display_ns - record.predicted_present_ns


def nearest_rank(values: list[float], k: int) -> float:
    return sorted(values)[max(1, math.ceil(k / 100 * len(values))) - 1]


def run(tmp_path: Path, trace: str, horizon_ms: float = 0.0, **method) -> tuple[dict, list[FrameRecord]]:
    """A virtual-time run of FRAMES VSyncs of `trace` (replayed once), through hmdrt.api; its report and the
    records of its frames log. horizon_ms 0: the gaze is not predicted, each frame renders its newest sample."""
    log = tmp_path / "frames.jsonl"
    config = write_config(
        tmp_path / "run.toml",
        {"name": "rrm", **method},
        trace=trace,
        drivers=[{"url": f"replay://{Path(trace).resolve()}"}],
        prediction={"horizon_ms": horizon_ms},
        output={"frames_log": str(log)},
    )
    report = run_compositor(config, FRAMES).to_dict()
    reading = read_frames_log(log)
    errors = reading.gaze_errors()
    for record in reading.records:  # each record, with its own VSync's error, for the checks
        record.gaze_errors = [errors[record.vsync]] if record.vsync in errors else []
    return report, reading.records


def test_a_pursuit_rendered_without_prediction_is_seen_its_velocity_times_its_lag_behind(tmp_path):
    speeds = {"left": 20.0, "right": -10.0}  # deg/s, the eyes apart: each eye is measured on its own
    start = {"left": -10.0, "right": 5.0}
    eyes = [
        tuple(direction(start[eye] + speeds[eye] * k * SAMPLE_NS / 1e9) for eye in ("left", "right")) + (True,)
        for k in range(400)
    ]
    report, records = run(tmp_path, gaze_trace(tmp_path / "pursuit.jsonl", eyes, SAMPLE_NS))

    errors = report[KEY]
    resolved = [r for r in records if r.gaze_errors]
    # every VSync but the last ones, whose photon time no sample came after before the run ended
    assert errors["resolved"] == len(resolved) >= FRAMES - 3
    assert errors["resolved"] + errors["unresolved"] == report["vsyncs"] == FRAMES
    assert errors["held"] == errors["waiting"] == 0
    assert [r.vsync for r in resolved] == list(range(len(resolved)))
    for eye, speed in speeds.items():
        expected = []
        for record in resolved:
            lag_s = (photon_ns(record) - record.gaze.t_host) / 1e9  # the newest sample, held to the photon time
            assert 0.04 < lag_s < 0.06  # a period to wake-up, half a period to mid-display, the samples' spacing
            expected.append(abs(speed) * lag_s)
            error = record.gaze_errors[0]
            assert getattr(error, f"{eye}_deg") == pytest.approx(expected[-1], abs=1e-4)
            assert error.fovea_deg == 10.0  # rrm's fovea_deg
        for k in (50, 95, 99):  # the histogram's percentiles: nearest rank, to 0.12%, in thousandths of a degree
            assert errors[eye][f"p{k}"] == pytest.approx(nearest_rank(expected, k), rel=2e-3, abs=1e-3)
        assert errors[eye]["max"] == pytest.approx(max(expected), abs=1e-3)
        assert errors[eye]["beyond_fovea"] == 0.0
    assert_gaze_error_within(report, p95_deg=1.1, beyond_fovea=0.0)
    with pytest.raises(AssertionError, match=r"left eye's gaze error p50 1\.0\d\d deg, over 0\.5 deg"):
        assert_gaze_error_within(report, p50_deg=0.5)


def test_the_same_pursuit_predicted_to_the_photon_time_is_seen_where_it_was_rendered(tmp_path):
    eyes = [(direction(-10 + 20.0 * k * SAMPLE_NS / 1e9),) * 2 + (True,) for k in range(400)]
    report, _ = run(tmp_path, gaze_trace(tmp_path / "pursuit.jsonl", eyes, SAMPLE_NS), horizon_ms=100.0)
    assert report[KEY]["resolved"] >= FRAMES - 3
    assert_gaze_error_within(report, max_deg=0.005)  # 20 deg/s, predicted over ~52 ms from a constant velocity


def test_a_gaze_step_is_seen_at_its_full_size_until_a_frame_rendered_after_it_is_shown(tmp_path):
    step_deg, step_ns = 12.0, 212_000_000  # no photon time falls between the last sample before and the first after
    eyes = [(direction(step_deg if k * SAMPLE_NS >= step_ns else 0.0),) * 2 + (True,) for k in range(400)]
    report, records = run(tmp_path, gaze_trace(tmp_path / "step.jsonl", eyes, SAMPLE_NS))

    errors = report[KEY]
    resolved = [r for r in records if r.gaze_errors]
    seen = []
    for record in resolved:
        assert not step_ns - SAMPLE_NS < photon_ns(record) < step_ns
        rendered_after, seen_after = record.gaze.t_host >= step_ns, photon_ns(record) >= step_ns
        expected = step_deg if seen_after and not rendered_after else 0.0
        assert record.gaze_errors[0].left_deg == pytest.approx(expected, abs=1e-6)
        seen.append(expected)
    assert seen.count(step_deg) >= 1  # the frames rendered before the step and shown after it
    assert errors["left"]["max"] == errors["right"]["max"] == pytest.approx(step_deg, abs=1e-3)
    share = round(seen.count(step_deg) / len(seen), 5)  # past rrm's 10 degree fovea
    assert errors["left"]["beyond_fovea"] == errors["right"]["beyond_fovea"] == share
    with pytest.raises(AssertionError, match="beyond the foveal radius"):
        assert_gaze_error_within(report, beyond_fovea=0.0)


def test_vsyncs_seen_in_a_blink_are_held_and_those_after_the_trace_ends_unresolved_never_guessed(tmp_path):
    samples, blink = 150, range(59, 81)  # 600 ms of trace; invalid (eyes closed) from 236 to 320 ms
    eyes = [(direction(0.0),) * 2 + (k not in blink,) for k in range(samples)]
    report, records = run(tmp_path, gaze_trace(tmp_path / "blink.jsonl", eyes, SAMPLE_NS))

    errors = report[KEY]
    newest = [photon_ns(r) // SAMPLE_NS for r in records]  # the newest sample at or before each photon time
    held = [k in blink or k + 1 in blink for k in newest]  # one of the samples either side said the eyes were shut
    ended = [k >= samples - 1 for k in newest]  # no sample after it
    assert blink.start - 1 in newest  # a photon time between the last sample with the eyes open and the blink
    assert errors["held"] == sum(held) >= 3
    assert errors["unresolved"] == sum(ended) >= 10
    assert errors["resolved"] == FRAMES - sum(held) - sum(ended) and errors["waiting"] == 0
    assert [r.vsync for r in records if r.gaze_errors] == [
        r.vsync for r, h, e in zip(records, held, ended, strict=True) if not h and not e
    ]


# --- the sink on its own ------------------------------------------------------------------------------------------


class Clock:
    def __init__(self) -> None:
        self.t = 0

    def now_ns(self) -> int:
        return self.t


def shown(vsync: int, present_ns: int, method: str = "rrm", params: dict | None = None, gaze=None) -> Shown:
    """A VSync's Shown with what the sink reads: its times (display 5 ms after present), method, and the frame's
    gaze (None: rendered straight ahead)."""
    times = dict.fromkeys(("predicted_wake_ns", "actual_wake_ns", "render_start_ns", "render_end_ns"), 0)
    record = FrameRecord(
        vsync=vsync,
        frame_id=vsync,
        shown="new",
        actual_present_ns=present_ns,
        predicted_present_ns=present_ns,
        predicted_display_ns=present_ns + 5_000_000,
        missed=False,
        gaze=None,
        pose=None,
        method=method,
        params={"fovea_deg": 2.0} if params is None else params,
        **times,
    )
    return Shown(record, [], SimpleNamespace(gaze_dirs=gaze))


def feed(store: SampleStore, until_ns: int, degrees: float = 3.0) -> None:
    """Gaze samples every 4 ms up to until_ns, `degrees` to the right, each received as it is captured."""
    for t in range(0, until_ns + 1, SAMPLE_NS):
        store.add("eye", Gaze(seq=t // SAMPLE_NS, t_host=t, C=direction(degrees)), t)


def test_a_vsync_waits_for_a_sample_after_its_photon_time_and_one_that_never_comes_is_given_up():
    store, clock = SampleStore(history_ns=100_000_000), Clock()
    sink = GazeErrors(store, clock, ("left", "right"), lambda: "")
    feed(store, 40_000_000)
    clock.t = 40_000_000
    first = shown(0, 30_000_000)  # photon at 35 ms: bracketed
    sink.offer(first)
    assert [(e.vsync, round(e.left_deg, 6), e.fovea_deg) for e in first.record.gaze_errors] == [(0, 3.0, 2.0)]
    late = shown(1, 40_000_000)  # photon at 45 ms: nothing captured after it yet
    sink.offer(late)
    assert late.record.gaze_errors == [] and sink.report()[KEY]["waiting"] == 1
    clock.t = 150_000_000  # the tracker silent for longer than the store keeps samples: given up, not guessed
    sink.offer(shown(2, 150_000_000))
    report = sink.report()[KEY]
    assert (report["resolved"], report["unresolved"], report["waiting"]) == (1, 1, 1)
    sink.finish()  # the run ends: what still waits is counted
    report = sink.report()[KEY]
    assert (report["resolved"], report["unresolved"], report["waiting"]) == (1, 2, 0)
    assert report["left"]["p50"] == report["right"]["max"] == 3.0 and report["left"]["beyond_fovea"] == 1.0


def test_the_queue_is_bounded_and_a_burst_of_late_samples_is_settled_a_bounded_number_at_a_time():
    store, clock = SampleStore(history_ns=10_000_000_000), Clock()  # nothing waits long enough to be given up
    sink = GazeErrors(store, clock, ("left",), lambda: "", max_waiting=100)
    period = 10_000_000
    for vsync in range(120):  # the tracker stalled: nothing arrives, the oldest are pushed out
        clock.t = vsync * period
        sink.offer(shown(vsync, vsync * period))
    assert sink.report()[KEY]["unresolved"] == 20 and sink.report()[KEY]["waiting"] == 100
    feed(store, 120 * period)  # then it all arrives at once
    clock.t = 120 * period
    burst = shown(120, 120 * period)  # pushes out one more
    sink.offer(burst)
    assert [e.vsync for e in burst.record.gaze_errors] == list(range(21, 21 + MOST_PER_VSYNC))
    assert all(e.right_deg is None for e in burst.record.gaze_errors)  # the display shows the left eye only
    sink.finish()  # settles the rest; the burst's own VSync is after the newest sample
    report = sink.report()[KEY]
    assert report["resolved"] == 99 and report["unresolved"] == 22 and "right" not in report


def test_the_share_beyond_the_fovea_counts_frames_with_a_fovea_only_and_is_null_without_one():
    store, clock = SampleStore(), Clock()
    sink = GazeErrors(store, clock, ("left", "right"), lambda: "")
    feed(store, 100_000_000)
    clock.t = 100_000_000
    rendered = {"left": np.array(direction(3.0)), "right": np.array(direction(3.0))}
    sink.offer(shown(0, 10_000_000, "full", {}))  # straight ahead, 3 degrees off, no fovea to be beyond
    assert sink.report()[KEY]["left"]["beyond_fovea"] is None
    sink.offer(shown(1, 20_000_000, "rrm", {"fovea_deg": 5.0}))  # 3 degrees off, within
    sink.offer(shown(2, 30_000_000, "rrm", {"fovea_deg": 2.0}))  # 3 degrees off, beyond
    sink.offer(shown(3, 40_000_000, "rrm", {"fovea_deg": 2.0}, gaze=rendered))  # rendered where the eye was
    report = sink.report()[KEY]
    assert report["left"]["beyond_fovea"] == report["right"]["beyond_fovea"] == round(1 / 3, 5)
    assert report["left"]["max"] == 3.0 and report["left"]["p50"] == pytest.approx(3.0, abs=4e-3)
    assert report["resolved"] == 4


def test_assert_gaze_error_within_needs_a_bound_a_measure_and_a_fovea_for_the_share():
    report = {KEY: {"left": {"p95": 1.0, "beyond_fovea": None}, "resolved": 0, "held": 3, "unresolved": 2}}
    with pytest.raises(TypeError, match="give a bound"):
        assert_gaze_error_within(report)
    with pytest.raises(AssertionError, match="no gaze error at photon time was measured .0 VSyncs resolved, 3 held"):
        assert_gaze_error_within(report, p95_deg=2.0)
    report[KEY]["resolved"] = 10
    assert_gaze_error_within(report, p95_deg=1.0)
    with pytest.raises(AssertionError, match="the method has no foveal radius"):
        assert_gaze_error_within(report, beyond_fovea=0.5)
