"""What an eye tracker reports of a true gaze: a model of its four published figures of merit.

- Accuracy: a fixed angular offset per recording and eye (a calibration error), of the accuracy's magnitude in a
  seeded random direction; the mean reported gaze of a fixation lies that far from the true one.
- Precision: RMS sample-to-sample noise (RMS-S2S, the figure makers and evaluations publish: Holmqvist, Nystrom &
  Mulvey 2012, "Eye tracker data quality", ETRA). White noise of standard deviation precision / 2 on each of two
  axes has an RMS distance between successive samples of precision.
- Sampling rate: the tracker samples at multiples of its period, each sample the true gaze at that time (the
  latest true sample at or before it: sample and hold).
- Data loss: dropouts of a fixed length (loss_ms) starting at random, so that loss_rate of the samples are
  invalid; between dropouts the waits are exponential (a renewal process).

A true gaze is a GazeSequence: timestamped unit directions per eye and a validity flag (blinks stay invalid).
Tracker.report turns it into the reported sequence, deterministically for a seed. The sampling (Sampling), the
noise's scale (white_noise) and the presets' look-up (preset_named) are the head tracker model's too
(hmdrt.tracking.pose).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, TypeVar

import msgspec
import numpy as np

RATE_SLACK = 0.01  # a tracker may sample up to 1% faster than the true sequence (clock jitter in a recording)
FORWARD = (0.0, 0.0, -1.0)  # the direction an invalid sample holds: it means nothing
T = TypeVar("T")


@dataclass(frozen=True)
class GazeSequence:
    """Timestamped gaze per eye: t_ns (n,) int64 rising, left and right (n, 3) unit directions in the head
    frame, valid (n,) bool (an invalid sample's directions are FORWARD and mean nothing)."""

    t_ns: np.ndarray
    left: np.ndarray
    right: np.ndarray
    valid: np.ndarray

    @property
    def rate_hz(self) -> float | None:
        """The sequence's sampling rate (sampling_rate_hz)."""
        return sampling_rate_hz(self.t_ns)


def sampling_rate_hz(t_ns: np.ndarray) -> float | None:
    """The rate of samples at times t_ns: 1 / their median interval; None with fewer than two samples."""
    if len(t_ns) < 2:
        return None
    return 1e9 / float(np.median(np.diff(t_ns)))


class Sampling:
    """What every tracker model does alike, eye or head: it samples a true sequence at rate_hz (inf: every true
    sample; a field of the model), each of its samples the latest true sample at or before it (sample and hold),
    and it may not sample faster than the truth it reports."""

    __slots__ = ()
    rate_hz: float

    @property
    def period_ns(self) -> int | None:
        """The sampling period in whole nanoseconds (samples fall on its multiples); None at an infinite rate."""
        return None if math.isinf(self.rate_hz) else round(1e9 / self.rate_hz)

    def check_rate(self, truth_hz: float | None, what: str) -> None:
        """ValueError where the tracker samples faster than `truth_hz`, the rate of `what` it reports: it would
        repeat samples and show no motion between them."""
        if truth_hz is not None and self.rate_hz > truth_hz * (1.0 + RATE_SLACK):
            raise ValueError(
                f"rate_hz {self.rate_hz:g} is faster than {what}, sampled at {truth_hz:.4g} Hz; "
                f"allowed: a tracker of at most {truth_hz:.4g} Hz"
            )

    def sample(self, t_ns: np.ndarray, what: str) -> tuple[np.ndarray, np.ndarray]:
        """The times of the tracker's samples of `what`, a true sequence sampled at t_ns, and the index of the true
        sample each one reports: every true sample at an infinite rate, else the multiples of the period from the
        first at or after t_ns[0] to t_ns[-1]. ValueError where the truth has no samples or is sampled slower."""
        if len(t_ns) == 0:
            raise ValueError(f"{what} has no samples")
        period = self.period_ns
        if period is None:
            return t_ns, np.arange(len(t_ns))
        self.check_rate(sampling_rate_hz(t_ns), what)
        t = np.arange(-(-int(t_ns[0]) // period), int(t_ns[-1]) // period + 1, dtype=np.int64) * period
        return t, np.searchsorted(t_ns, t, side="right") - 1


def white_noise(rng: np.random.Generator, rms_s2s: float, shape: tuple[int, ...]) -> np.ndarray:
    """Gaussian white noise of `shape` (samples first, the axes of one sample's error last) whose RMS
    sample-to-sample distance is rms_s2s: a standard deviation of rms_s2s / sqrt(2 axes) on each axis, as the
    difference of two independent samples has twice the variance of each."""
    return rng.normal(0.0, rms_s2s / math.sqrt(2.0 * shape[-1]), size=shape)


def preset_named(presets: dict[str, T], name: str, key: str, table: type) -> T:
    """The preset of that name; ValueError naming `key`, the presets and the fields of a `table` for another."""
    try:
        return presets[name]
    except KeyError:
        raise ValueError(
            f"{key} {name!r} is no preset; presets: {', '.join(presets)}, "
            f"or a table of {', '.join(table.__struct_fields__)}"
        ) from None


class Tracker(msgspec.Struct, Sampling, frozen=True, forbid_unknown_fields=True):
    """An eye tracker's errors. The defaults are a perfect tracker: no offset, no noise, every true sample
    reported (rate_hz = inf), nothing lost."""

    accuracy_deg: Annotated[float, msgspec.Meta(ge=0.0, le=30.0)] = 0.0
    precision_deg: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.0  # RMS sample to sample
    rate_hz: Annotated[float, msgspec.Meta(ge=1.0)] = math.inf  # inf: every true sample
    loss_rate: Annotated[float, msgspec.Meta(ge=0.0, lt=1.0)] = 0.0  # the fraction of samples lost
    loss_ms: Annotated[float, msgspec.Meta(ge=0.0, le=10_000.0)] = 0.0  # the length of each dropout

    def __post_init__(self) -> None:
        if self.loss_rate > 0.0 and self.loss_ms <= 0.0:
            raise ValueError(f"loss_rate {self.loss_rate:g} needs a dropout length: loss_ms > 0")

    def report(self, truth: GazeSequence, seed: int | Sequence[int] = 0) -> GazeSequence:
        """What the tracker reports of `truth` (ValueError where it samples faster than truth): its samples from
        the first multiple of its period at or after truth's first sample to its last, each offset, noisy, and
        invalid where truth is or where a dropout falls. The same seed gives the same samples."""
        t, pick = self.sample(truth.t_ns, "the true gaze")
        rng = np.random.default_rng(seed)
        bias = math.radians(self.accuracy_deg) * _directions(rng.uniform(0.0, 2.0 * math.pi, size=2))  # (eye, 2)
        noise = white_noise(rng, math.radians(self.precision_deg), (len(t), 2, 2))  # (sample, eye, 2)
        valid = truth.valid[pick] & ~self._lost(t, rng)
        left, right = (_deflect(d[pick], bias[e] + noise[:, e]) for e, d in enumerate((truth.left, truth.right)))
        left[~valid] = right[~valid] = FORWARD
        return GazeSequence(t, left, right, valid)

    def _lost(self, t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Which of the samples at times t fall in a dropout: loss_ms long each, after exponential waits of mean
        loss_ms (1 - loss_rate) / loss_rate, so that loss_rate of the time is lost."""
        lost = np.zeros(len(t), dtype=bool)
        if self.loss_rate == 0.0 or len(t) == 0:
            return lost
        length = self.loss_ms * 1e6
        wait = length * (1.0 - self.loss_rate) / self.loss_rate
        start = t[0] + rng.exponential(wait)
        while start <= t[-1]:
            lost[np.searchsorted(t, start) : np.searchsorted(t, start + length)] = True
            start += length + rng.exponential(wait)
        return lost


def _directions(angles: np.ndarray) -> np.ndarray:
    """Unit 2-vectors (n, 2) at these angles (radians) from the horizontal axis."""
    return np.stack([np.cos(angles), np.sin(angles)], axis=-1)


def _deflect(d: np.ndarray, by: np.ndarray) -> np.ndarray:
    """Unit directions d (n, 3) each turned by the angle |by| (radians) towards by's direction in the tangent
    plane (by (n, 2): rightward, upward); a zero turn leaves d exactly as it was."""
    d = np.array(d, dtype=np.float64)
    angle = np.hypot(by[:, 0], by[:, 1])
    moved = angle > 0.0
    if not moved.any():
        return d
    d0, by, angle = d[moved], by[moved], angle[moved, None]
    right = np.cross(d0, (0.0, 1.0, 0.0))
    flat = np.linalg.norm(right, axis=1) < 1e-9  # looking straight up or down: "right" is the head's +x
    right[flat] = (1.0, 0.0, 0.0)
    right /= np.linalg.norm(right, axis=1, keepdims=True)
    up = np.cross(right, d0)
    toward = (by[:, :1] * right + by[:, 1:] * up) / angle
    turned = np.cos(angle) * d0 + np.sin(angle) * toward
    d[moved] = turned / np.linalg.norm(turned, axis=1, keepdims=True)
    return d
