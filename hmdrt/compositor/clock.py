"""The compositor's clocks: host time (drivers/base.py's Clock and MonotonicClock, re-exported), simulated
time for --virtual-time runs, and the display's vsync grid. All times are integer host-monotonic nanoseconds.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers.base import MONOTONIC, Clock, MonotonicClock

__all__ = ["MONOTONIC", "Clock", "MonotonicClock", "VirtualClock", "VsyncClock"]


class VirtualClock:
    """Simulated time that only the compositor moves (Monado tests/time_utils.hpp MockClock).

    sleep_until returns at once and leaves time alone: drivers share this clock and must not move it.
    """

    def __init__(self, t0_ns: int):
        self._t_ns = int(t0_ns)

    def now_ns(self) -> int:
        return self._t_ns

    def sleep_until(self, t_ns: int) -> None:
        """Return at once; virtual time passes only through advance_to."""

    def advance_to(self, t_ns: int) -> None:
        """Move time forward to t_ns; ValueError if that is in the past (time never goes back)."""
        if t_ns < self._t_ns:
            raise ValueError(f"virtual time never goes back: asked for {t_ns} ns, it is already {self._t_ns} ns")
        self._t_ns = int(t_ns)


@dataclass(frozen=True)
class VsyncClock:
    """The display's vertical syncs, at t0_ns + k * period_ns for every integer k."""

    period_ns: int
    t0_ns: int

    def __post_init__(self) -> None:
        if not isinstance(self.period_ns, int) or self.period_ns <= 0:
            raise ValueError(f"vsync period must be a positive integer of nanoseconds, got {self.period_ns!r}")
        if not isinstance(self.t0_ns, int):
            raise ValueError(f"vsync t0 must be an integer of nanoseconds, got {self.t0_ns!r}")

    def vsync(self, k: int) -> int:
        """The time of vsync k."""
        return self.t0_ns + k * self.period_ns

    def index_at_or_after(self, t_ns: int) -> int:
        """The index of the first vsync at or after t_ns (t_ns itself when it falls on one)."""
        return -((self.t0_ns - t_ns) // self.period_ns)

    def next_after(self, t_ns: int) -> int:
        """The time of the first vsync strictly after t_ns."""
        return self.vsync((t_ns - self.t0_ns) // self.period_ns + 1)
