"""Mapping device time to host time: an online offset-and-drift estimate per driver.

Each sample pairs its device timestamp with the host time it was received. Receive time = capture
time + latency, where the latency has a floor and a jittery excess; the lower envelope of
(t_recv - t_dev) follows the floor. The estimate keeps the minimum of each window of device time
and fits a line (offset and drift) through the last windows' minima, so jitter, dropped samples and
bursts barely move it (the windowed-minimum idea of Monado's m_clock_tracking and of NTP). A window
whose minimum sits well above the line (the host stalled for the whole window) is left out of the
fit, drift is fitted only once the minima span min_span_ns (before that, a few noisy windows make
wild slopes), and no capture time is ever mapped later than its own receive time.

The latency floor itself cannot be seen in one-way timestamps: the envelope maps a sample to
capture + floor. A known device latency (floor_ns), or round-trip probes of the device clock where
the protocol has them (probe(), as Pupil's `t` and NTP do), take it out. Counters that wrap are
unwrapped; a device reset (its time jumping backwards, or forwards by more than reset_ns against
the host) starts the estimate afresh.
"""

from __future__ import annotations

import math
import statistics
from collections import deque

from hmdrt.bus.messages import ClockEstimate


class ClockSync:
    def __init__(
        self,
        window_ns: int = 250_000_000,
        windows: int = 32,
        wrap_ns: int | None = None,
        reset_ns: int = 2_000_000_000,
        min_span_ns: int = 2_000_000_000,
        floor_ns: int = 0,
    ):
        self.window_ns = window_ns
        self.wrap_ns = wrap_ns
        self.reset_ns = reset_ns
        self.min_span_ns = min_span_ns
        self.floor_ns = floor_ns
        self._minima: deque[tuple[int, int]] = deque(maxlen=windows)  # (t_dev, t_recv - t_dev)
        self._window: tuple[int, int, int] | None = None  # (start t_dev, t_dev at min, min delta)
        self._last_raw: int | None = None
        self._wraps = 0
        self._last: tuple[int, int] | None = None  # (t_dev, t_recv) of the previous pair
        self._fit = (0.0, 0.0, 0, 0.0)  # offset, drift (ns/ns), reference t_dev, residual
        self._probe: tuple[int, int, int] | None = None  # (rtt, t_dev, host time at t_dev) of the best probe
        self.pairs = 0
        self.resets = 0

    def unwrap(self, t_dev_raw: int) -> int:
        """Device time continued across counter wrap-arounds (when wrap_ns is set)."""
        if self.wrap_ns is None:
            return t_dev_raw
        if self._last_raw is not None and t_dev_raw < self._last_raw - self.wrap_ns // 2:
            self._wraps += 1
        self._last_raw = t_dev_raw
        return t_dev_raw + self._wraps * self.wrap_ns

    def reset(self) -> None:
        self._minima.clear()
        self._window = None
        self._last = None
        self._fit = (0.0, 0.0, 0, 0.0)
        self._probe = None
        self.pairs = 0
        self.resets += 1

    def probe(self, t_send: int, t_dev_raw: int, t_reply: int) -> None:
        """A round trip: the device read its clock (t_dev_raw) between the host's t_send and t_reply.
        The device time is taken to fall mid-way, within rtt/2; the fastest probe is kept."""
        rtt = t_reply - t_send
        if rtt < 0:
            raise ValueError(f"probe reply before its request ({rtt} ns)")
        if self._probe is None or rtt <= self._probe[0]:
            self._probe = (rtt, self.unwrap(t_dev_raw), (t_send + t_reply) // 2)

    def add(self, t_dev_raw: int, t_recv: int) -> int:
        """Record a (device time, receive time) pair; returns the sample's capture time on the host clock."""
        t_dev = self.unwrap(t_dev_raw)
        if self._last is not None:
            dd, dr = t_dev - self._last[0], t_recv - self._last[1]
            if dd < -1_000_000 or abs(dd - dr) > self.reset_ns:
                self.reset()
                self._last_raw = t_dev_raw
                self._wraps = 0
                t_dev = t_dev_raw
        self._last = (t_dev, t_recv)
        self.pairs += 1
        delta = t_recv - t_dev
        if self._window is None:
            self._window = (t_dev, t_dev, delta)
        elif t_dev - self._window[0] >= self.window_ns:
            self._minima.append((self._window[1], self._window[2]))
            self._refit()
            self._window = (t_dev, t_dev, delta)
        elif delta < self._window[2]:
            self._window = (self._window[0], t_dev, delta)
        return min(self.to_host(t_dev, unwrapped=True), t_recv)

    def _refit(self) -> None:
        ref = self._minima[0][0]
        xs = [float(t - ref) for t, _ in self._minima]  # at most `windows` of them: plain Python is quickest
        ys = [float(d) for _, d in self._minima]
        kept = range(len(xs))
        for _ in range(2):  # leave out windows far above the envelope: the host stalled through them
            offset, drift = self._line([xs[i] for i in kept], [ys[i] for i in kept])
            excess = [y - offset - drift * x for x, y in zip(xs, ys, strict=True)]
            limit = 3.0 * statistics.median(abs(excess[i]) for i in kept) + 50_000.0
            kept = [i for i, e in enumerate(excess) if e <= limit]
        offset, drift = self._line([xs[i] for i in kept], [ys[i] for i in kept])
        misfit = sum((ys[i] - offset - drift * xs[i]) ** 2 for i in kept) / len(kept)
        self._fit = (offset, drift, ref, math.sqrt(misfit))

    def _line(self, xs: list[float], ys: list[float]) -> tuple[float, float]:
        """Offset and drift through the minima (least squares); a flat lower bound until they span min_span_ns."""
        if len(xs) >= 3 and xs[-1] - xs[0] >= self.min_span_ns:
            mx, my = sum(xs) / len(xs), sum(ys) / len(ys)
            drift = sum((x - mx) * (y - my) for x, y in zip(xs, ys, strict=True)) / sum((x - mx) ** 2 for x in xs)
            return my - drift * mx, drift
        return min(ys), 0.0

    def _envelope(self, t_dev: int) -> float:
        """t_recv - t_dev of the lower envelope at device time t_dev."""
        if not self._minima:
            return float(self._window[2]) if self._window else 0.0
        offset, drift, ref, _ = self._fit
        return offset + drift * (t_dev - ref)

    def _floor(self) -> float:
        """The latency floor the envelope includes: the best probe's, else the configured one."""
        if self._probe is None or self.pairs == 0:
            return float(self.floor_ns)
        _, t_dev, t_host = self._probe
        return self._envelope(t_dev) - (t_host - t_dev)

    def to_host(self, t_dev: int, unwrapped: bool = False) -> int:
        """Host capture time of a device timestamp under the current estimate."""
        if not unwrapped:
            t_dev = t_dev if self.wrap_ns is None else t_dev + self._wraps * self.wrap_ns
        return int(round(t_dev + self._envelope(t_dev) - self._floor()))

    def estimate(self) -> ClockEstimate | None:
        if self.pairs == 0:
            return None
        _, drift, ref, residual = self._fit
        return ClockEstimate(
            offset_ns=self._envelope(ref) - self._floor(),
            drift_ppm=drift * 1e6,
            residual_ns=residual,
            t_ref_ns=ref,
            pairs=self.pairs,
            floor_ns=self._floor(),
        )
