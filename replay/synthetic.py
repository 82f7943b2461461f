"""Seeded synthetic gaze and head motion, sample by sample at a tracker rate.

Eye movement is a sequence of events: fixations (log-normal durations, mean about 250 ms) with slow
drift and occasional microsaccades (0.1-0.5 deg); saccades on the main sequence (duration 21 + 2.2 A
ms for amplitude A in degrees, after Carpenter 1988) with a minimum-jerk position profile (peak
velocity 1.875 A / D); smooth pursuit of a target moving at 5-20 deg/s; blinks of 150-300 ms whose
samples are invalid. Microsaccades follow the main sequence too. The tracker adds a constant accuracy
offset and Gaussian precision noise (its latency is the driver's: drivers.synthetic releases a sample
that long after its capture). The two eyes converge on a fixation depth, so left and right gaze
differ by the vergence.
The head turns slowly (smoothed random yaw and pitch) with a little jitter. Everything is a pure
function of the seed, so a run reproduces exactly.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from hmdrt.bus.messages import Gaze, Pose
from hmdrt.spatial import gaze_direction, quat_from_yaw_pitch


def saccade_duration_s(amplitude_deg: float) -> float:
    """The main sequence: duration 21 ms + 2.2 ms per degree (Carpenter 1988)."""
    return 0.021 + 0.0022 * amplitude_deg


def minimum_jerk(tau: float) -> float:
    """Fraction of the movement done at normalised time tau in [0, 1]."""
    tau = min(max(tau, 0.0), 1.0)
    return tau**3 * (10.0 - 15.0 * tau + 6.0 * tau * tau)


@dataclass(frozen=True)
class SyntheticConfig:
    seed: int = 0
    rate_hz: float = 250.0
    field_deg: float = 20.0  # fixation targets lie within +-field_deg of straight ahead
    noise_deg: float = 0.1  # precision: Gaussian noise per sample
    offset_deg: tuple[float, float] = (0.0, 0.0)  # accuracy: constant (yaw, pitch) error
    blink_rate_hz: float = 0.25
    pursuit_share: float = 0.15  # share of events that are smooth pursuit
    ipd_m: float = 0.0635
    head: bool = True


class SyntheticSource:
    """Gaze samples (and head poses) at rate_hz from t0_ns; iterate with samples()."""

    def __init__(self, config: SyntheticConfig = SyntheticConfig()):
        if not (1.0 <= config.rate_hz <= 10_000.0):
            raise ValueError(f"rate must be within 1 and 10000 Hz, got {config.rate_hz}")
        self.config = config
        self._rng = np.random.default_rng(config.seed)
        self._yaw, self._pitch = 0.0, 0.0
        self._depth = 1.5
        self._event_end = 0.0
        self._event = ("fixation", 0.0, 0.0, 0.0, 0.0, 0.0)  # kind, start, from yaw/pitch, to yaw/pitch
        self._micro: tuple[float, ...] | None = None  # start, from yaw/pitch, to yaw/pitch, end
        self._blink_until = -1.0
        self._next_blink = self._rng.exponential(1.0 / config.blink_rate_hz) if config.blink_rate_hz > 0 else math.inf
        self._head_phase = self._rng.uniform(0, 2 * math.pi, 4)

    def _new_event(self, t: float) -> None:
        rng, cfg = self._rng, self.config
        self._micro = None
        if rng.random() < cfg.pursuit_share:
            speed = rng.uniform(5.0, 20.0)
            heading = rng.uniform(0, 2 * math.pi)
            duration = rng.uniform(0.5, 1.5)
            to = (self._yaw + speed * duration * math.cos(heading), self._pitch + speed * duration * math.sin(heading))
            to = tuple(float(np.clip(v, -cfg.field_deg, cfg.field_deg)) for v in to)
            self._event = ("pursuit", t, self._yaw, self._pitch, *to)
            self._event_end = t + duration
            return
        if self._event[0] == "fixation":
            target = rng.uniform(-cfg.field_deg, cfg.field_deg, 2)
            amplitude = math.hypot(target[0] - self._yaw, target[1] - self._pitch)
            self._event = ("saccade", t, self._yaw, self._pitch, float(target[0]), float(target[1]))
            self._event_end = t + saccade_duration_s(amplitude)
            self._depth = float(rng.uniform(0.5, 5.0))
            return
        duration = float(np.clip(rng.lognormal(math.log(0.25), 0.35), 0.1, 1.0))
        self._event = ("fixation", t, self._yaw, self._pitch, self._yaw, self._pitch)
        self._event_end = t + duration

    def _eye(self, t: float) -> tuple[float, float]:
        kind, start, y0, p0, y1, p1 = self._event
        if kind == "saccade":
            s = minimum_jerk((t - start) / max(self._event_end - start, 1e-9))
        elif kind == "pursuit":
            s = min(max((t - start) / max(self._event_end - start, 1e-9), 0.0), 1.0)
        else:
            return self._fixation(t)
        return y0 + s * (y1 - y0), p0 + s * (p1 - p0)

    def _fixation(self, t: float) -> tuple[float, float]:
        """Gaze during a fixation: slow drift (about 0.05 deg/s) and a microsaccade about every 0.8 s."""
        kind, start, y0, p0, y1, p1 = self._event
        micro = self._micro
        if micro is not None and t >= micro[5]:  # the microsaccade is over: the fixation continues from there
            y0, p0 = micro[3], micro[4]
            self._event, micro = (kind, start, y0, p0, y1, p1), None
        if micro is None and self._rng.random() < 1.0 / (0.8 * self.config.rate_hz):
            to = (y0 + self._rng.normal(0, 0.2), p0 + self._rng.normal(0, 0.2))
            micro = (t, y0, p0, *to, t + saccade_duration_s(math.hypot(to[0] - y0, to[1] - p0)))
        self._micro = micro
        if micro is not None:
            s = minimum_jerk((t - micro[0]) / (micro[5] - micro[0]))
            y0, p0 = micro[1] + s * (micro[3] - micro[1]), micro[2] + s * (micro[4] - micro[2])
        return y0 + 0.05 * (t - start), p0

    def head_pose(self, t: float) -> tuple[float, float]:
        """Head yaw and pitch (deg): slow turns from summed low-frequency sines, plus jitter."""
        if not self.config.head:
            return 0.0, 0.0
        ph = self._head_phase
        yaw = 12.0 * math.sin(2 * math.pi * 0.07 * t + ph[0]) + 4.0 * math.sin(2 * math.pi * 0.23 * t + ph[1])
        pitch = 4.0 * math.sin(2 * math.pi * 0.05 * t + ph[2]) + 1.5 * math.sin(2 * math.pi * 0.31 * t + ph[3])
        return yaw + self._rng.normal(0, 0.02), pitch + self._rng.normal(0, 0.02)

    def samples(self, t0_ns: int = 0, count: int | None = None) -> Iterator[Gaze | Pose]:
        """Gaze (and, with head motion, pose) messages in time order; t_host and t_dev in ns from t0_ns."""
        cfg = self.config
        k = 0
        while count is None or k < count:
            t = k / cfg.rate_hz
            if t >= self._event_end:
                self._new_event(t)
            self._yaw, self._pitch = self._eye(t)
            if t >= self._next_blink and self._blink_until < t:
                self._blink_until = t + self._rng.uniform(0.15, 0.3)
                self._next_blink = self._blink_until + self._rng.exponential(1.0 / cfg.blink_rate_hz)
            t_host = t0_ns + round(t * 1e9)
            valid = t >= self._blink_until
            yaw = self._yaw + cfg.offset_deg[0] + self._rng.normal(0, cfg.noise_deg)
            pitch = self._pitch + cfg.offset_deg[1] + self._rng.normal(0, cfg.noise_deg)
            centre = np.array(gaze_direction(yaw, pitch))
            target = centre * self._depth
            half = np.array([cfg.ipd_m / 2, 0.0, 0.0])
            left, right = target + half, target - half  # from each eye (at -+ half) to the target
            yield Gaze(
                seq=k,
                t_host=t_host,
                t_dev=t_host,
                valid=valid,
                C=tuple(centre),
                L=tuple(left / np.linalg.norm(left)),
                R=tuple(right / np.linalg.norm(right)),
                depth_m=self._depth,
            )
            if cfg.head:
                hy, hp = self.head_pose(t)
                yield Pose(
                    seq=k,
                    t_host=t_host,
                    t_dev=t_host,
                    position=(0.0, 0.0, 0.0),
                    orientation=quat_from_yaw_pitch(hy, hp),
                )
            k += 1
