"""Lab Streaming Layer, shared by the lsl:// driver, `hmdrt emulate lsl` and the compositor's [lsl] outlets: pylsl
loaded on first use (the optional `lsl` extra), and LSL time against the host clock.

LSL time is liblsl's local_clock() in seconds: std::chrono::steady_clock, which on Linux reads CLOCK_MONOTONIC, the
clock of time.monotonic_ns (sccn/liblsl src/common.cpp, lsl_local_clock_ns @ 64988c6; tests/test_lsl.py checks it on
the machine that runs them). hmdrt relies on that only where ClockMap.measure() finds the two agree; elsewhere it
measures their offset.
"""

from __future__ import annotations

from dataclasses import dataclass
from types import ModuleType

from hmdrt.clock import Clock, MonotonicClock
from hmdrt.errors import ConfigError

INSTALL = "pip install 'hmdrt[lsl]'"
SHARED_NS = 1_000_000  # clocks whose readings agree this closely are one clock
READS = 7  # bracketed readings per offset measurement; the tightest bracket is kept


def load_pylsl() -> ModuleType:
    """pylsl, with its bundled liblsl; a ConfigError naming the extra when either cannot be loaded."""
    try:
        import pylsl
    except (ImportError, OSError, RuntimeError) as exc:  # pylsl raises RuntimeError when it finds no liblsl
        raise ConfigError(f"Lab Streaming Layer needs pylsl and liblsl ({INSTALL}): {exc}") from None
    return pylsl


@dataclass(frozen=True)
class ClockMap:
    """LSL time (s) against a hmdrt clock (ns): lsl = (t + offset_ns) / 1e9. `shared`: the clock is the host's
    monotonic clock and local_clock() reads the same, so offset_ns is exactly 0."""

    offset_ns: int
    shared: bool

    @classmethod
    def measure(cls, clock: Clock) -> ClockMap:
        """The offset of local_clock() from `clock`, read between two readings of `clock` (the tightest of READS
        brackets); a virtual clock gets the offset of its current time, fixed from then on."""
        local_clock = load_pylsl().local_clock
        brackets = []
        for _ in range(READS):
            before = clock.now_ns()
            lsl_ns = round(local_clock() * 1e9)
            after = clock.now_ns()
            brackets.append((after - before, lsl_ns - (before + after) // 2))
        width, offset = min(brackets)
        shared = isinstance(clock, MonotonicClock) and abs(offset) <= SHARED_NS + width
        return cls(0 if shared else offset, shared)

    def to_lsl(self, t_ns: int) -> float:
        """A time of the clock as LSL time in seconds."""
        return (t_ns + self.offset_ns) / 1e9

    def to_clock(self, t_lsl: float) -> int:
        """LSL time in seconds as a time of the clock in nanoseconds."""
        return round(t_lsl * 1e9) - self.offset_ns
