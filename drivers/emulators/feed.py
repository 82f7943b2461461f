"""What an emulated tracker sees: gaze from a trace or the synthetic generator, degraded like a real
tracker (constant accuracy offset, precision noise, latency) and resampled to the device's rate.

A trace is held sample-and-hold at the device rate from its first sample and loops; the synthetic
generator runs at the device rate itself. A sample captured at t is due at t + latency: the emulator
sends it then, stamped with its capture time on the emulated device's own clock.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from hmdrt.bus.messages import Gaze, usable
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.errors import ConfigError
from hmdrt.replay import load_trace
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource
from hmdrt.spatial import Vec, gaze_direction


@dataclass(frozen=True)
class FeedSample:
    index: int  # device frame number
    capture_ns: int  # on the feed's clock
    due_ns: int  # capture + latency: when the device delivers it
    left: np.ndarray | None  # unit gaze directions, head frame; None when not valid
    right: np.ndarray | None
    valid: bool
    depth_m: float | None


def _degrade(direction: Vec, offset_deg: float, noise: np.ndarray) -> Vec:
    """Rotate a gaze direction by a constant yaw offset plus noise (yaw, pitch) in degrees."""
    yaw = np.degrees(np.arctan2(direction[0], -direction[2])) + offset_deg + noise[0]
    pitch = np.degrees(np.arcsin(np.clip(direction[1], -1.0, 1.0))) + noise[1]
    return gaze_direction(yaw, pitch)


class GazeFeed:
    def __init__(
        self,
        rate_hz: float,
        trace: str | None = None,
        seed: int = 0,
        offset_deg: float = 0.0,
        noise_deg: float = 0.0,
        latency_ms: float = 0.0,
        clock: Clock = MONOTONIC,
    ):
        if not 1.0 <= rate_hz <= 10_000.0:
            raise ConfigError(f"device rate must be within 1 and 10000 Hz, got {rate_hz}")
        self.rate_hz = rate_hz
        self.clock = clock
        self.latency_ns = int(latency_ms * 1e6)
        self._rng = np.random.default_rng(seed)
        self.offset_deg, self.noise_deg = offset_deg, noise_deg
        if trace is None:
            source = SyntheticSource(SyntheticConfig(seed=seed, rate_hz=rate_hz, head=False))
            self._gaze = (s for s in source.samples() if isinstance(s, Gaze))
        else:
            samples = [s for s in load_trace(trace).samples if isinstance(s, Gaze)]
            if not samples:
                raise ConfigError(f"trace {trace} holds no gaze samples")
            self._gaze = self._resampled(sorted(samples, key=lambda s: s.t_host))

    def _resampled(self, samples: list[Gaze]) -> Iterator[Gaze]:
        """Sample-and-hold at the device rate, looping the trace."""
        t0, span = samples[0].t_host, max(samples[-1].t_host - samples[0].t_host, 1)
        period, k, j = 1e9 / self.rate_hz, 0, 0
        while True:
            t = (k * period) % (span + period)
            j = 0 if t < samples[min(j, len(samples) - 1)].t_host - t0 else j
            while j + 1 < len(samples) and samples[j + 1].t_host - t0 <= t:
                j += 1
            yield samples[j]
            k += 1

    def samples(self) -> Iterator[FeedSample]:
        """Feed samples from now on, each available once the clock reaches its due time."""
        start = self.clock.now_ns()
        period = 1e9 / self.rate_hz
        for k, gaze in enumerate(self._gaze):
            capture = start + round(k * period)
            noise = self._rng.normal(0.0, self.noise_deg, 2) if self.noise_deg else np.zeros(2)
            valid = usable(gaze)
            left = right = None
            if valid:
                eyes = gaze.eye_directions()
                if self.offset_deg or self.noise_deg:
                    eyes = tuple(_degrade(v, self.offset_deg, noise) for v in eyes)
                left, right = (np.array(v) for v in eyes)
            yield FeedSample(k, capture, capture + self.latency_ns, left, right, valid, gaze.depth_m)
