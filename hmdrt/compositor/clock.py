"""The display's vsync grid; the clocks themselves are hmdrt.clock's. Integer host-monotonic nanoseconds."""

from __future__ import annotations

from dataclasses import dataclass


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
