"""Frame pacing for the compositor's single renderer: when to wake, which vsync to target and which display time to
predict, closed on measured render times and present margins.

Adapted from Monado's display-timing compositor pacer (src/xrt/auxiliary/util/u_pacing_compositor.c), with the
render-time filter and period multiples of its app pacer (u_pacing_app.c); numbers in docs/architecture.md, Pacer.
One addition: a ray tracer's frame times vary far more than a compositor's GPU work (a CPU renderer on a shared
machine: p99 often 1.5 to 2 times p50), and a budget on the filtered mean then misses about every other frame
while the slack hunts. With tail_quantile set, the wake-up plans for the larger of the IIR mean and that
quantile of the last tail_window render times, as far as the frame interval allows: the tail moves the wake-up
earlier, while the frame interval still follows the mean (a few slow frames are misses, not half the rate).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from typing import TYPE_CHECKING

from hmdrt.clock import VirtualClock
from hmdrt.compositor.clock import VsyncClock
from hmdrt.errors import ConfigError

if TYPE_CHECKING:
    from hmdrt.compositor.config import Pacing

ALPHA = 0.8  # IIR weight on the old render estimate (u_pacing_app.c, anchors: "IIR alpha 0.8")
MISS_THRESHOLD_NS = 500_000  # later than this past the desired present is a miss (u_pacing_compositor.c)
MISS_STEP_FRACTION = 0.04  # slack growth after a miss (u_pacing_compositor.c adjust_missed_fraction)
NUDGE_FRACTION = 0.02  # slack nudge band and step otherwise (u_pacing_compositor.c adjust_non_miss_fraction)
HYSTERESIS_FRACTION = 0.1  # how far under a shorter interval the work must fall before pacing returns to it
HISTORY = 16  # frames remembered between predict and presented (u_pacing_compositor.c NUM_FRAMES)


@dataclass(frozen=True)
class FrameTiming:
    """One frame's schedule, as predict() hands it out."""

    frame_id: int
    wake_ns: int  # when to start the frame (sample gaze/pose, then render)
    desired_present_ns: int  # the vsync this frame targets
    predicted_display_ns: int  # desired_present + present_to_display_ns (OpenXR: mid display interval)
    period_ns: int  # the display period
    budget_ns: int  # render estimate + slack + margin the wake-up was computed from
    vsyncs: int  # frame interval in display periods (1 normally; >1 when the work cannot fit in one)


@dataclass
class _Frame:
    timing: FrameTiming
    render_end_ns: int | None = None


class Pacer:
    """Schedules frames against a vsync grid and learns from how they turned out.

    Call predict(now) for each frame, sleep until its wake_ns, render, then mark_render() and presented().
    Budget = filtered render time + adaptive slack + fixed margin; the slack closes the loop on present margins.
    """

    def __init__(
        self,
        vsync: VsyncClock,
        present_to_display_ns: int | None = None,
        margin_ns: int = 1_000_000,
        initial_fraction: float = 0.5,
        max_fraction: float = 1.0,
        *,
        alpha: float = ALPHA,
        miss_threshold_ns: int = MISS_THRESHOLD_NS,
        miss_step_fraction: float = MISS_STEP_FRACTION,
        nudge_fraction: float = NUDGE_FRACTION,
        hysteresis_fraction: float = HYSTERESIS_FRACTION,
        tail_quantile: float | None = None,
        tail_window: int = 64,
    ):
        """present_to_display_ns defaults to half the period: OpenXR's predictedDisplayTime is the middle of the
        display interval (Monado guesses 4 ms). max_fraction is the share of the frame interval the budget may use;
        initial_fraction is the render estimate, as a share of the period, until the first measurement."""
        period = vsync.period_ns
        for name, value in (("initial_fraction", initial_fraction), ("max_fraction", max_fraction)):
            if not 0 < value <= 1:
                raise ValueError(f"{name} must be within (0, 1] of the period, got {value}")
        for name, value in (("miss_step_fraction", miss_step_fraction), ("nudge_fraction", nudge_fraction)):
            if not 0 < value < 1:
                raise ValueError(f"{name} must be within (0, 1) of the period, got {value}")
        if not 0 <= alpha < 1:
            raise ValueError(f"alpha must be within [0, 1), got {alpha}")
        if miss_threshold_ns < 0:
            raise ValueError(f"miss_threshold_ns must be >= 0, got {miss_threshold_ns}")
        if not 0 <= hysteresis_fraction < 1:
            raise ValueError(f"hysteresis_fraction must be within [0, 1), got {hysteresis_fraction}")

        self._vsync = vsync
        self._room_ns = max_fraction * period
        self._alpha = alpha
        self._miss_threshold_ns = int(miss_threshold_ns)
        self._miss_step_ns = round(miss_step_fraction * period)
        self._nudge_ns = round(nudge_fraction * period)
        self._hysteresis_ns = hysteresis_fraction * period

        self._render_ns = initial_fraction * period  # the IIR-filtered mean
        self._recent: deque[int] = deque()
        self._measured = False
        self._slack_ns = 0
        self._vsyncs = 1
        self.configure(
            margin_ns=margin_ns,
            present_to_display_ns=present_to_display_ns,
            tail_quantile=tail_quantile,
            tail_window=tail_window,
        )
        self._next_id = 0
        self._frames: dict[int, _Frame] = {}
        self._last_index: int | None = None
        self._not_before_ns: int | None = None
        self._misses = 0
        self._presented = 0

    def configure(
        self,
        *,
        margin_ns: int,
        present_to_display_ns: int | None = None,
        tail_quantile: float | None = None,
        tail_window: int = 64,
    ) -> None:
        """Set the margin, the display offset and the tail planning, also between frames (a reloaded config);
        the render times learned so far are kept."""
        period = self._vsync.period_ns
        if present_to_display_ns is None:
            present_to_display_ns = period // 2
        if present_to_display_ns < 0:
            raise ValueError(f"present_to_display_ns must be >= 0, got {present_to_display_ns}")
        if not 0 <= margin_ns < period:
            raise ValueError(f"margin_ns must be within [0, period {period}), got {margin_ns}")
        if tail_quantile is not None and not 0 < tail_quantile <= 1:
            raise ValueError(f"tail_quantile must be within (0, 1], got {tail_quantile}")
        if tail_window < 1:
            raise ValueError(f"tail_window must be >= 1, got {tail_window}")
        self._present_to_display_ns = int(present_to_display_ns)
        self._margin_ns = int(margin_ns)
        self._tail_quantile = tail_quantile
        self._recent = deque(self._recent, maxlen=tail_window)
        self._update_vsyncs()

    @property
    def margin_ns(self) -> int:
        """The fixed margin kept before each VSync."""
        return self._margin_ns

    @property
    def present_to_display_ns(self) -> int:
        """How long after its present a frame is predicted to be seen (added to desired present for display time)."""
        return self._present_to_display_ns

    def predict(self, now_ns: int) -> FrameTiming:
        """The next frame's schedule: the earliest vsync one frame interval after the last target (and after the
        last actual present) whose wake-up is not in the past; when behind, whole periods are skipped
        (u_pacing_compositor.c walk_forward_through_frames)."""
        budget = self._budget_ns()
        index = self._vsync.index_at_or_after(now_ns + budget)
        if self._last_index is not None:
            index = max(index, self._last_index + self._vsyncs)
        if self._not_before_ns is not None:
            index = max(index, self._vsync.index_at_or_after(self._not_before_ns + 1))
        self._last_index = index
        present = self._vsync.vsync(index)
        timing = FrameTiming(
            frame_id=self._next_id,
            wake_ns=present - budget,
            desired_present_ns=present,
            predicted_display_ns=present + self._present_to_display_ns,
            period_ns=self._vsync.period_ns,
            budget_ns=budget,
            vsyncs=self._vsyncs,
        )
        self._next_id += 1
        self._frames[timing.frame_id] = _Frame(timing)
        if len(self._frames) > HISTORY:
            del self._frames[next(iter(self._frames))]
        return timing

    def mark_render(self, frame_id: int, start_ns: int, end_ns: int) -> None:
        """Record when a frame's render ran; feeds the render-time filter (IIR, u_pacing_app.c). The first
        measurement replaces the initial guess rather than being blended with it."""
        frame = self._frame(frame_id)
        if end_ns < start_ns:
            raise ValueError(f"frame {frame_id}: render end {end_ns} ns is before its start {start_ns} ns")
        if frame.render_end_ns is not None:
            raise ValueError(f"frame {frame_id}: render already marked")
        frame.render_end_ns = end_ns
        took_ns = end_ns - start_ns
        self._render_ns = self._alpha * self._render_ns + (1 - self._alpha) * took_ns if self._measured else took_ns
        self._recent.append(took_ns)
        self._measured = True
        self._update_vsyncs()

    def presented(self, frame_id: int, actual_present_ns: int) -> bool:
        """Record when a frame reached the display; True when it missed (u_pacing_compositor.c adjust_comp_time).

        A miss grows the slack by a large step; otherwise, with the render marked, a present margin outside the
        target's nudge band moves the slack one small step toward it. The slack stays within [0, one period].
        """
        frame = self._frame(frame_id)
        del self._frames[frame_id]
        desired = frame.timing.desired_present_ns
        missed = actual_present_ns - desired > self._miss_threshold_ns
        if missed:
            self._misses += 1
            self._slack_ns += self._miss_step_ns
        elif frame.render_end_ns is not None:
            off_target_ns = (desired - frame.render_end_ns) - self._margin_ns
            if off_target_ns > self._nudge_ns:
                self._slack_ns -= self._nudge_ns
            elif off_target_ns < -self._nudge_ns:
                self._slack_ns += self._nudge_ns
        # A display that reports every frame late (blanked, say) must not drive the frame interval up without bound.
        self._slack_ns = min(max(self._slack_ns, 0), self._vsync.period_ns)
        self._presented += 1
        # Presents within the miss threshold of a vsync belong to it, so the next target lies beyond that.
        not_before = actual_present_ns + self._miss_threshold_ns
        self._not_before_ns = not_before if self._not_before_ns is None else max(self._not_before_ns, not_before)
        self._update_vsyncs()
        return missed

    def info(self) -> dict[str, int | bool]:
        """The pacer's current state, for stats and logs."""
        return {
            "period_ns": self._vsync.period_ns,
            "render_estimate_ns": math.ceil(self._estimate_ns()),
            "slack_ns": self._slack_ns,
            "margin_ns": self._margin_ns,
            "budget_ns": self._budget_ns(),
            "vsyncs": self._vsyncs,
            "fits": self._vsyncs == 1,
            "misses": self._misses,
            "presented": self._presented,
        }

    def _estimate_ns(self) -> float:
        """The render time the wake-up plans for: the filtered mean, or the tail quantile when that is larger."""
        if self._tail_quantile is None or not self._recent:
            return self._render_ns
        if self._tail_quantile >= 1.0:
            tail = max(self._recent)
        else:
            ordered = sorted(self._recent)
            tail = ordered[min(len(ordered) - 1, math.ceil(self._tail_quantile * len(ordered)) - 1)]
        return max(self._render_ns, tail)

    def _mean_budget_ns(self) -> int:
        return math.ceil(self._render_ns) + self._slack_ns + self._margin_ns

    def _budget_ns(self) -> int:
        """How long before its present a frame wakes: the tail estimate, within the frame interval."""
        budget = math.ceil(self._estimate_ns()) + self._slack_ns + self._margin_ns
        return max(self._mean_budget_ns(), min(budget, math.floor(self._vsyncs * self._room_ns)))

    def _update_vsyncs(self) -> None:
        """Frame interval = the smallest multiple of the period whose max_fraction covers the budget (u_pacing_app.c;
        anchors: drop to a multiple rather than miss repeatedly); it shrinks only once the budget fits the shorter
        interval with the hysteresis to spare, so it does not flap."""
        budget = self._mean_budget_ns()
        up = max(1, math.ceil(budget / self._room_ns))
        down = max(1, math.ceil((budget + self._hysteresis_ns) / self._room_ns))
        self._vsyncs = max(up, min(self._vsyncs, down))

    def _frame(self, frame_id: int) -> _Frame:
        frame = self._frames.get(frame_id)
        if frame is None:
            raise ValueError(
                f"frame {frame_id} is unknown to the pacer (never predicted, already presented, "
                f"or older than the last {HISTORY} frames)"
            )
        return frame


def pacing_settings(pacing: Pacing, period_ns: int) -> dict:
    """A Pacer's settings from the [pacing] section, checked against the display period (ConfigError)."""
    period_ms = period_ns / 1e6
    if pacing.margin_ms >= period_ms:
        raise ConfigError(f"pacing.margin_ms = {pacing.margin_ms} must be shorter than the period {period_ms:.2f} ms")
    offset = pacing.present_to_display_ms
    return {
        "margin_ns": int(pacing.margin_ms * 1e6),
        "present_to_display_ns": None if offset < 0 else int(offset * 1e6),
        "tail_quantile": pacing.tail_quantile or None,
        "tail_window": pacing.tail_window,
    }


def replay_frame(pacer: Pacer, clock: VirtualClock, render_ns: int) -> tuple[FrameTiming, int, bool]:
    """One frame of a renderer on a virtual clock: wake when the pacer says, render for render_ns, present at the
    first VSync at or after the end; (timing, actual present, missed). The pacing tests and bench/pacing.py
    (measured render times replayed) run the pacer through this."""
    t = pacer.predict(clock.now_ns())
    clock.advance_to(t.wake_ns)  # raises if the pacer scheduled a wake-up in the past
    end = t.wake_ns + render_ns
    pacer.mark_render(t.frame_id, t.wake_ns, end)
    vsync = pacer._vsync
    actual = t.desired_present_ns if end <= t.desired_present_ns else vsync.vsync(vsync.index_at_or_after(end))
    missed = pacer.presented(t.frame_id, actual)
    clock.advance_to(end)
    return t, actual, missed
