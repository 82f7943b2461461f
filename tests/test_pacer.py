"""The frame pacer and the compositor clocks, on virtual time (after Monado's tests_pacing.cpp with MockClock)."""

import random

import pytest

from hmdrt.clock import VirtualClock
from hmdrt.compositor.clock import VsyncClock
from hmdrt.compositor.pacer import HISTORY, FrameTiming, Pacer, replay_frame

PERIOD = 11_111_111  # 90 Hz
MS = 1_000_000
NUDGE = round(0.02 * PERIOD)
MISS_STEP = round(0.04 * PERIOD)


class Display:
    """One renderer on a virtual clock: wake, render for render_ns, present at the first vsync at or after the end."""

    def __init__(self, pacer: Pacer | None = None, t0_ns: int = 0):
        self.vsync = VsyncClock(PERIOD, t0_ns)
        self.clock = VirtualClock(t0_ns)
        self.pacer = pacer or Pacer(self.vsync)
        self.log: list[tuple[FrameTiming, int, bool, dict]] = []

    def frame(self, render_ns: int) -> bool:
        t, actual, missed = replay_frame(self.pacer, self.clock, render_ns)
        self.log.append((t, actual, missed, self.pacer.info()))
        return missed

    def run(self, render_ns: int, frames: int) -> list[bool]:
        return [self.frame(render_ns) for _ in range(frames)]


def test_vsync_clock_index_arithmetic():
    v = VsyncClock(100, 1000)
    assert (v.vsync(0), v.vsync(3), v.vsync(-1)) == (1000, 1300, 900)
    assert v.index_at_or_after(1000) == 0  # exactly on a vsync
    assert v.index_at_or_after(1001) == 1
    assert v.index_at_or_after(999) == 0
    assert v.index_at_or_after(900) == -1
    assert v.index_at_or_after(899) == -1
    assert v.next_after(1000) == 1100  # strictly after, even on a vsync
    assert v.next_after(999) == 1000
    assert v.next_after(850) == 900
    for period in (0, -5, 1.5):
        with pytest.raises(ValueError, match="period"):
            VsyncClock(period, 0)


def test_virtual_clock_never_goes_back_and_sleep_does_not_move_it():
    c = VirtualClock(5_000)
    c.sleep_until(1_000_000)
    assert c.now_ns() == 5_000
    c.advance_to(5_000)
    c.advance_to(7_000)
    assert c.now_ns() == 7_000
    with pytest.raises(ValueError, match="never goes back"):
        c.advance_to(6_999)
    assert c.now_ns() == 7_000
    c.advance(500)
    assert c.now_ns() == 7_500
    with pytest.raises(ValueError, match="never goes back"):
        c.advance(-1)


def test_first_prediction_relations():
    vsync = VsyncClock(PERIOD, 3_000)
    now = 50 * MS + 17
    t = Pacer(vsync).predict(now)
    assert t.budget_ns == -(-PERIOD // 2) + 1 * MS  # half-period estimate + 1 ms margin
    assert (t.vsyncs, t.period_ns) == (1, PERIOD)
    assert t.wake_ns == t.desired_present_ns - t.budget_ns
    assert (t.desired_present_ns - 3_000) % PERIOD == 0
    assert t.wake_ns >= now > t.wake_ns - PERIOD  # the earliest vsync whose wake-up is not past
    assert t.predicted_display_ns == t.desired_present_ns + PERIOD // 2
    assert Pacer(vsync).present_to_display_ns == PERIOD // 2
    t4 = Pacer(vsync, present_to_display_ns=4 * MS).predict(now)
    assert t4.predicted_display_ns == t4.desired_present_ns + 4 * MS


def test_steady_render_converges_without_misses():
    d = Display()
    misses = d.run(6 * MS, 500)
    assert not any(misses)
    info = d.pacer.info()
    assert abs(info["render_estimate_ns"] - 6 * MS) <= 1
    assert abs(info["budget_ns"] - 7 * MS) <= NUDGE + 1
    presents = [t.desired_present_ns for t, *_ in d.log]
    assert {b - a for a, b in zip(presents, presents[1:], strict=False)} == {PERIOD}  # every vsync used
    assert (info["misses"], info["presented"], info["fits"]) == (0, 500, True)


def test_render_step_up_misses_briefly_then_slack_recovers_slowly():
    d = Display()
    assert not any(d.run(4 * MS, 50))
    misses = d.run(9 * MS, 100)
    assert misses[0]
    assert 1 <= sum(misses) <= 4 and not any(misses[4:])
    slack = [info["slack_ns"] for *_, info in d.log[50:]]
    peak = max(slack)
    assert peak >= 3 * MISS_STEP
    after = slack[slack.index(peak) :]
    assert all(a - b <= NUDGE for a, b in zip(after, after[1:], strict=False))  # shrinks one nudge a frame at most
    settle = next(i for i, s in enumerate(after) if s <= NUDGE)
    assert settle >= (peak - NUDGE) // NUDGE
    assert after[-1] <= NUDGE


def test_targets_strictly_later_vsyncs_under_jitter():
    rng = random.Random(7)
    d = Display(t0_ns=123_456)
    for _ in range(500):
        d.frame(
            rng.choice((15 * MS, rng.randint(2 * MS, 10 * MS))) if rng.random() < 0.05 else rng.randint(2 * MS, 9 * MS)
        )
    previous_present = previous_actual = None
    for t, actual, _, _ in d.log:
        assert (t.desired_present_ns - 123_456) % PERIOD == 0
        assert t.predicted_display_ns == t.desired_present_ns + PERIOD // 2
        assert t.budget_ns <= t.vsyncs * PERIOD
        if previous_present is not None:
            assert t.desired_present_ns > previous_present
            assert t.desired_present_ns > previous_actual
        previous_present, previous_actual = t.desired_present_ns, actual


def test_steps_whole_periods_when_behind():
    pacer = Pacer(VsyncClock(PERIOD, 0))
    first = pacer.predict(0)
    late = first.desired_present_ns + 10 * PERIOD + 300_000
    t = pacer.predict(late)
    assert (t.desired_present_ns - first.desired_present_ns) % PERIOD == 0
    assert t.wake_ns >= late > t.wake_ns - PERIOD


def test_slow_renders_drop_to_two_vsyncs_then_come_back():
    d = Display()
    misses = d.run(13 * MS, 200)
    assert sum(misses) <= 2 and not any(misses[2:])
    steady = d.log[5:]
    assert all(t.vsyncs == 2 for t, *_ in steady)
    assert {b[0].desired_present_ns - a[0].desired_present_ns for a, b in zip(steady, steady[1:], strict=False)} == {
        2 * PERIOD
    }
    assert d.pacer.info()["fits"] is False

    assert not any(d.run(4 * MS, 100))
    assert d.pacer.info()["fits"] is True
    back = next(i for i, (t, *_) in enumerate(d.log[200:]) if t.vsyncs == 1)
    assert back <= 10
    tail = d.log[200 + back :]
    assert all(t.vsyncs == 1 for t, *_ in tail)
    assert {b[0].desired_present_ns - a[0].desired_present_ns for a, b in zip(tail, tail[1:], strict=False)} == {PERIOD}


def test_interval_holds_within_hysteresis_band():
    # 9.5 ms + 1 ms margin fits one 11.1 ms period, but not with the 1.1 ms hysteresis to spare.
    fresh = Display()
    fresh.run(9_500_000, 100)
    assert all(t.vsyncs == 1 for t, *_ in fresh.log[1:])
    assert fresh.pacer.info()["misses"] == 1  # the first frame, against the initial half-period guess

    d = Display()
    d.run(13 * MS, 50)
    assert not any(d.run(9_500_000, 200))
    held = [t.desired_present_ns for t, *_ in d.log[50:] if t.vsyncs == 2]
    assert len(held) == 200
    assert {b - a for a, b in zip(held, held[1:], strict=False)} == {2 * PERIOD}  # a steady cadence, no 1-2-1 judder
    d.run(8 * MS, 20)
    assert d.pacer.info()["vsyncs"] == 1


def test_miss_threshold_is_half_a_millisecond():
    pacer = Pacer(VsyncClock(PERIOD, 0))
    t = pacer.predict(0)
    pacer.mark_render(t.frame_id, t.wake_ns, t.desired_present_ns - 1 * MS)
    assert pacer.presented(t.frame_id, t.desired_present_ns + 500_000) is False
    t = pacer.predict(t.desired_present_ns)
    pacer.mark_render(t.frame_id, t.wake_ns, t.desired_present_ns - 1 * MS)
    assert pacer.presented(t.frame_id, t.desired_present_ns + 500_001) is True
    assert pacer.info()["misses"] == 1


def test_slack_steps():
    pacer = Pacer(VsyncClock(PERIOD, 0))
    now = 0

    def frame(margin_ns: int | None, late_ns: int = 0) -> int:
        nonlocal now
        t = pacer.predict(now)
        if margin_ns is not None:
            end = t.desired_present_ns - margin_ns
            pacer.mark_render(t.frame_id, end - 100_000, end)
        pacer.presented(t.frame_id, t.desired_present_ns + late_ns)
        now = t.desired_present_ns + late_ns
        return pacer.info()["slack_ns"]

    assert frame(None, late_ns=PERIOD) == MISS_STEP  # a miss, with or without a render mark
    assert frame(5 * MS) == MISS_STEP - NUDGE  # far more margin than the 1 ms target: one nudge down
    assert frame(5 * MS) == 0
    assert frame(5 * MS) == 0  # never negative
    assert frame(1 * MS - NUDGE - 1) == NUDGE  # below the band: one nudge up
    assert frame(1 * MS + NUDGE) == NUDGE  # within the band: unchanged
    assert frame(None) == NUDGE  # no render mark, no margin to act on
    for _ in range(40):
        frame(None, late_ns=PERIOD)
    assert pacer.info()["slack_ns"] == PERIOD  # capped at one period


@pytest.mark.parametrize(
    "kwargs",
    [
        {"margin_ns": -1},
        {"margin_ns": PERIOD},
        {"present_to_display_ns": -1},
        {"initial_fraction": 0},
        {"initial_fraction": 1.5},
        {"max_fraction": 0},
        {"max_fraction": 1.01},
        {"alpha": 1.0},
        {"miss_threshold_ns": -1},
        {"hysteresis_fraction": 1.0},
        {"nudge_fraction": 0},
    ],
)
def test_rejects_bad_settings(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        Pacer(VsyncClock(PERIOD, 0), **kwargs)


def test_rejects_bad_calls():
    pacer = Pacer(VsyncClock(PERIOD, 0))
    t = pacer.predict(0)
    with pytest.raises(ValueError, match="before its start"):
        pacer.mark_render(t.frame_id, 10, 9)
    with pytest.raises(ValueError, match="unknown"):
        pacer.mark_render(t.frame_id + 1, 0, 1)
    pacer.mark_render(t.frame_id, 0, 1)
    with pytest.raises(ValueError, match="already marked"):
        pacer.mark_render(t.frame_id, 0, 1)
    pacer.presented(t.frame_id, t.desired_present_ns)
    with pytest.raises(ValueError, match="unknown"):
        pacer.presented(t.frame_id, t.desired_present_ns)

    first = pacer.predict(0)
    for _ in range(HISTORY):
        pacer.predict(0)
    with pytest.raises(ValueError, match="unknown"):
        pacer.mark_render(first.frame_id, 0, 1)


def test_configure_changes_margin_and_offset_between_frames_and_keeps_what_was_learned():
    d = Display()
    d.run(6 * MS, 200)
    before = d.pacer.info()
    d.pacer.configure(margin_ns=3 * MS, present_to_display_ns=2 * MS)
    after = d.pacer.info()
    assert after["render_estimate_ns"] == before["render_estimate_ns"]  # not back to the initial guess
    assert after["margin_ns"] == 3 * MS and after["budget_ns"] == before["budget_ns"] + 2 * MS
    t = d.pacer.predict(d.clock.now_ns())
    assert t.predicted_display_ns == t.desired_present_ns + 2 * MS
    assert t.desired_present_ns - t.wake_ns == after["budget_ns"]
    with pytest.raises(ValueError, match="margin_ns"):
        d.pacer.configure(margin_ns=PERIOD)


@pytest.mark.parametrize("window", [9, 99])
def test_planning_for_the_largest_of_the_last_w_render_times_misses_about_one_frame_in_w_plus_1(window):
    """Independent render times: a frame is the largest of itself and the W before it one time in W + 1."""
    rng = random.Random(3)
    pacer = Pacer(VsyncClock(PERIOD, 0), margin_ns=0, tail_quantile=1.0, tail_window=window)
    clock = VirtualClock(0)
    frames = 20_000
    misses = sum(replay_frame(pacer, clock, int(rng.uniform(0.2, 0.6) * PERIOD))[2] for _ in range(frames))
    assert 0.7 / (window + 1) < misses / frames < 1.1 / (window + 1)
