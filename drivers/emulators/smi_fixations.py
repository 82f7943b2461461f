"""Online fixation detection for the SMI emulator's ET_FIX (docs/protocols.md, SMI).

Dispersion-threshold identification (I-DT): a fixation is a run of samples whose x extent plus y extent
stays within the dispersion for at least the minimum duration; lost tracking ends it.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

from hmdrt.drivers.protocols.smi import FixationEnd, FixationStart


@dataclass
class _Run:
    """A fixation in progress: first and last sample time, bounding box and coordinate sums."""

    start_us: int
    end_us: int
    box: list[float]  # x min, x max, y min, y max
    sums: list[float]  # count, sum of x, sum of y

    def spread_with(self, x: float, y: float) -> float:
        b = self.box
        return max(b[1], x) - min(b[0], x) + max(b[3], y) - min(b[2], y)

    def add(self, t_us: int, x: float, y: float) -> None:
        b, s = self.box, self.sums
        self.end_us = t_us
        b[:] = [min(b[0], x), max(b[1], x), min(b[2], y), max(b[3], y)]
        s[:] = [s[0] + 1, s[1] + x, s[2] + y]

    def centre(self) -> tuple[float, float]:
        n, sx, sy = self.sums
        return round(sx / n, 2), round(sy / n, 2)


class FixationDetector:
    """Online dispersion-threshold fixation detection (I-DT: x extent + y extent <= disp px for at least
    dur ms) on one eye's point of regard; add() returns the ET_FIX / ET_EFX event a sample causes."""

    def __init__(self, eye: str, duration_ms: int, dispersion_px: int):
        self.eye, self.min_us, self.max_px = eye, duration_ms * 1000, dispersion_px
        self._window: deque[tuple[int, float, float]] = deque()  # candidate points before a fixation
        self._run: _Run | None = None

    def add(self, t_us: int, xy: tuple[float, float] | None) -> FixationStart | FixationEnd | None:
        """Feed one sample (xy None: the eye is not tracked)."""
        run = self._run
        if run is not None:
            if xy is not None and run.spread_with(*xy) <= self.max_px:
                run.add(t_us, *xy)
                return None
            self._run = None
            self._window.clear()
            if xy is not None:
                self._window.append((t_us, *xy))
            x, y = run.centre()
            duration_ms = round((run.end_us - run.start_us) / 1000)
            return FixationEnd(self.eye, run.start_us, run.end_us, duration_ms, x, y)
        if xy is None:
            self._window.clear()
            return None
        w = self._window
        w.append((t_us, *xy))
        while len(w) > 1 and self._spread(w) > self.max_px:
            w.popleft()
        if w[-1][0] - w[0][0] < self.min_us:
            return None
        xs, ys = [p[1] for p in w], [p[2] for p in w]
        self._run = _Run(w[0][0], w[-1][0], [min(xs), max(xs), min(ys), max(ys)], [len(w), sum(xs), sum(ys)])
        w.clear()
        return FixationStart(self.eye, self._run.start_us, *self._run.centre())

    @staticmethod
    def _spread(window: deque[tuple[int, float, float]]) -> float:
        xs, ys = [p[1] for p in window], [p[2] for p in window]
        return max(xs) - min(xs) + max(ys) - min(ys)
