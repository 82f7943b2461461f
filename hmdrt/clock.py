"""Time, in one place: the Clock every driver, emulator and the compositor take, the host's monotonic clock,
and a virtual clock that moves only when told (for --virtual-time runs and tests). All times are integer
host-monotonic nanoseconds (docs/architecture.md, Conventions).
"""

from __future__ import annotations

import time
from typing import Protocol


class Clock(Protocol):
    def now_ns(self) -> int: ...

    def sleep_until(self, t_ns: int) -> None:
        """Wait until now_ns() reaches t_ns (a virtual clock returns at once: its time does not pass)."""


class MonotonicClock:
    """The host clock: time.monotonic_ns()."""

    def now_ns(self) -> int:
        return time.monotonic_ns()

    def sleep_until(self, t_ns: int) -> None:
        delay = t_ns - time.monotonic_ns()
        if delay > 0:
            time.sleep(delay / 1e9)


MONOTONIC = MonotonicClock()


class VirtualClock:
    """Simulated time that only its owner moves (Monado tests/time_utils.hpp MockClock): the compositor in a
    virtual-time run, a test elsewhere.

    sleep_until returns at once and leaves time alone: drivers share this clock and must not move it.
    """

    def __init__(self, t0_ns: int = 0):
        self._t_ns = int(t0_ns)

    def now_ns(self) -> int:
        return self._t_ns

    def sleep_until(self, t_ns: int) -> None:
        """Return at once; virtual time passes only through advance_to and advance."""

    def advance_to(self, t_ns: int) -> None:
        """Move time forward to t_ns; ValueError if that is in the past (time never goes back)."""
        if t_ns < self._t_ns:
            raise ValueError(f"virtual time never goes back: asked for {t_ns} ns, it is already {self._t_ns} ns")
        self._t_ns = int(t_ns)

    def advance(self, dt_ns: int) -> None:
        """Move time forward by dt_ns >= 0."""
        self.advance_to(self._t_ns + dt_ns)
