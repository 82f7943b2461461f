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

import functools
from collections import deque

import numpy as np

from hmdrt.bus.messages import ClockEstimate
from hmdrt.kernels.jit import serial


@serial
def _line(x: np.ndarray, y: np.ndarray, min_span: float) -> tuple[float, float]:
    """Offset and drift through the minima (least squares); a flat lower bound until they span min_span
    (and while they all share one device time, where the slope is 0 / 0)."""
    if x.size >= 3 and x[-1] - x[0] >= min_span:
        dx = x - x.mean()
        spread = (dx * dx).sum()
        if spread > 0.0:
            drift = (dx * (y - y.mean())).sum() / spread
            return y.mean() - drift * x.mean(), drift
    return y.min(), 0.0


@serial
def _fit_envelope(x: np.ndarray, y: np.ndarray, min_span: float) -> tuple[float, float, float]:
    """Offset, drift and RMS residual of the line through the windows' minima, leaving out windows far
    above it (the host stalled through them). Compiled: it runs on the sample path, a few times a second."""
    keep = np.ones(x.size, dtype=np.bool_)
    for _ in range(2):
        offset, drift = _line(x[keep], y[keep], min_span)
        excess = y - (offset + drift * x)
        limit = 3.0 * np.median(np.abs(excess[keep])) + 50_000.0
        keep = excess <= limit
    offset, drift = _line(x[keep], y[keep], min_span)
    misfit = y[keep] - (offset + drift * x[keep])
    return offset, drift, np.sqrt((misfit * misfit).mean())


@functools.cache
def _warm() -> None:
    """Load the compiled fit now, not on the sample path (loading it takes a large part of a second)."""
    _fit_envelope(np.arange(3.0), np.zeros(3), 1.0)


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
        if window_ns <= 0 or windows < 1 or reset_ns <= 0 or min_span_ns < 0 or (wrap_ns is not None and wrap_ns <= 0):
            raise ValueError(
                "clock sync needs window_ns > 0, windows >= 1, reset_ns > 0, min_span_ns >= 0 and wrap_ns > 0 or None;"
                f" got {window_ns}, {windows}, {reset_ns}, {min_span_ns}, {wrap_ns}"
            )
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
        _warm()

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
        minima = np.array(self._minima, dtype=np.int64)
        x = (minima[:, 0] - minima[0, 0]).astype(np.float64)
        offset, drift, residual = _fit_envelope(x, minima[:, 1].astype(np.float64), float(self.min_span_ns))
        self._fit = (offset, drift, int(minima[0, 0]), residual)

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
