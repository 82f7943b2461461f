"""Saccade landing prediction: once a saccade decelerates, where and when it will land.

In a saccade the gaze turns at up to 500-800 deg/s, so a frame shown 20-50 ms after the newest gaze sample
misses the new fixation by degrees, and extrapolating the newest velocity overshoots as the eye decelerates.
Saccades are stereotyped, though: the main sequence ties peak velocity and duration to amplitude (Bahill, Clark
and Stark 1975, Math. Biosci. 24:191; the exponential form V = Vmax (1 - exp(-A / C)) is that of Baloh, Sills,
Kumley and Honrubia 1975, Neurology 25:1065), and the velocity profile grows more skewed with duration (Van
Opstal and Van Gisbergen 1987, Vision Res. 27:731). Arabadzhiyska, Tursun, Myszkowski, Seidel and Didyk (2017,
"Saccade landing position prediction for gaze-contingent rendering", ACM TOG 36(4):50) fit the observed part
of a saccade's velocity profile to a model of such profiles to predict its amplitude, and so its landing
point, in time to render the new fixation's fovea before the eye gets there.

SaccadePredictor does that for one gaze stream, sample by sample, without their per-user calibration:

- Onset: the gaze speed over the last span_ms (3 ms: 3 samples at 1 kHz, 1 at 250 Hz, which keeps a 1 kHz
  tracker's sample-to-sample noise of 20-60 deg/s under the threshold) exceeds onset_deg_s and is rising (the
  acceleration criterion). The sample span_ms earlier is the saccade's start point.
- Model: the angle from the start point is d(t) = A P((t - t0) / D), P the distribution function of a Beta(a,
  b) profile whose peak lies at a fraction of D falling from 0.5 at 25 ms to 0.2 at 100 ms and beyond (the
  skew Van Opstal and Van Gisbergen report; the linear form between those ends is this module's), with
  a + b = 6 (Beta(3, 3) is the minimum-jerk profile) and, at a prior cost, a peak 0.1 earlier or later and the
  flatter a + b = 3.5 of large saccades' plateaus.
- Fit: over candidate durations D (10-250 ms), shapes and start times t0 (up to 4 ms before the start point)
  the amplitude A is the least-squares one (d is linear in A), at least the angle covered so far. A candidate
  costs its squared residual / noise_deg^2, its shape's prior cost and ((ln D - ln D_ms(A)) / 0.25)^2, D_ms(A)
  the duration at which the profile's peak velocity A max P' / D is the main sequence's; the 0.25 lets a
  person's saccades run about 25% faster or slower than the main sequence's without calibration.
- Reliability: a prediction is made once the eye has slowed to 70% of the flight's peak speed (before the
  peak, saccades of 10 and of 20 deg fit the same rising flank, and the main sequence's saturation cannot tell
  them apart; just after it, profiles of other skews still fit: at 80%, first predictions on hmdrt's
  minimum-jerk saccades at 1 kHz were up to 70% off, at 70% up to 35%), the saccade has covered
  min_progress_deg, every candidate within 4 of the least cost (about a 95% region) predicts an amplitude
  within max(1 deg, 30%) of the cheapest's, the cheapest lies inside the grid of durations, its amplitude is at
  most max_amplitude_deg, and its velocity over the newest span is within max(60 deg/s, 25%) of the observed
  one. Otherwise update() returns None and the caller keeps its own estimate. So predictions come late, at
  about 60-90% of a saccade's duration: without the per-user calibration of Arabadzhiyska et al., an earlier
  one is a guess.
- End: the flight ends, with no prediction, when the speed falls below offset_deg_s, on an invalid sample (a
  blink), on a gap of more than max_gap_ms, or when the eye turns away from the saccade (the angle from the
  start point grows at less than half the speed: a blink's lid artefact, a curved re-direction); after such a
  turn or a flight longer than max_flight_ms no onset counts until the speed has fallen below offset_deg_s.

Directions are unit head-frame vectors (hmdrt.spatial); the model turns the start point about one axis (a
great circle), the axis from the start point to the newest sample. A fit costs about 0.2 ms (numpy, one core);
it runs at most once a millisecond and only once the eye has slowed, 5-10 times a saccade; other samples cost
about 2 us.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import lru_cache

import numpy as np

from hmdrt.spatial import Vec, angle_between, rotvec_between, turn

__all__ = ["Flight", "SaccadePredictor", "predict_gazes"]

S, MS = 1_000_000_000, 1_000_000  # nanoseconds per second and millisecond
DURATIONS_S = np.geomspace(0.010, 0.250, 28)  # the fit's candidate durations, 12% apart
# profile shapes tried at each duration: (peak fraction less peak_fraction(D), a + b of the Beta, prior cost)
SHAPES = ((0.0, 6.0, 0.0), (-0.1, 6.0, 1.0), (0.1, 6.0, 1.0), (0.0, 3.5, 1.5), (-0.1, 3.5, 2.5))
STARTS_BEFORE_S, START_STEP_S = 0.004, 0.002  # candidate start times from 4 ms before the start point
DURATION_SIGMA = 0.25  # the main-sequence prior's spread of ln D
COST_REGION = 4.0  # candidates within this of the least cost must agree on the amplitude
AGREE_DEG, AGREE_FRACTION = 1.0, 0.3  # to within max(this, this fraction of the amplitude)
DECELERATED = 0.7  # predict once the speed has fallen below this fraction of the flight's peak
VELOCITY_DEG_S, VELOCITY_FRACTION = 60.0, 0.25  # the fit's newest velocity must be within max(this, this x)
FIT_INTERVAL_NS = MS  # at most one fit a millisecond; between, the last prediction stands
MAX_FIT_SAMPLES = 24  # a longer flight is fitted to this many of its samples, evenly spread
TABLE_STEPS = 256  # P tabulated at this many steps of t / D per candidate
STEPS = np.linspace(0.0, 1.0, TABLE_STEPS + 1)


def peak_fraction(duration_s: float | np.ndarray) -> np.ndarray:
    """Where a saccade's velocity peaks, as a fraction of its duration: 0.5 up to 25 ms, falling linearly to 0.2
    at 100 ms and beyond (the skew of Van Opstal and Van Gisbergen 1987)."""
    return np.clip(0.5 - 0.3 * (np.asarray(duration_s) - 0.025) / 0.075, 0.2, 0.5)


def _beta(fraction: np.ndarray, total: float) -> tuple[np.ndarray, np.ndarray]:
    """Beta(a, b) with a + b = total and its mode (a - 1) / (a + b - 2) at fraction."""
    a = 1.0 + (total - 2.0) * fraction
    return a, total - a


def _reach(table: np.ndarray, fraction: float | np.ndarray) -> np.ndarray:
    """P at fractions of the duration (clamped to [0, 1]), interpolated in a profile's table."""
    return np.interp(np.clip(fraction, 0.0, 1.0), STEPS, table)


@dataclass(frozen=True)
class _Model:
    """What the fit needs, worked out once per main sequence: one row per candidate profile (a duration and a
    shape), and the main sequence's duration D_ms(A)."""

    durations: np.ndarray  # (rows,) seconds
    penalties: np.ndarray  # (rows,) the shape's prior cost
    tables: np.ndarray  # (rows, TABLE_STEPS + 1): P at t / D = k / TABLE_STEPS
    log_amplitudes: np.ndarray  # ln A (degrees), ascending
    log_durations: np.ndarray  # ln D_ms(A) (seconds) at each


@lru_cache(maxsize=8)
def _model(vmax_deg_s: float, c_deg: float, max_amplitude_deg: float) -> _Model:
    from scipy.special import beta, betainc  # here: 0.1 s to import, which the compositor pays only when used

    shapes, penalties = [], []
    for shift, total, penalty in SHAPES:
        a, b = _beta(np.clip(peak_fraction(DURATIONS_S) + shift, 0.1, 0.6), total)
        shapes.append(np.stack([a, b], axis=1))
        penalties.append(np.full(len(DURATIONS_S), penalty))
    shape = np.concatenate(shapes)
    tables = betainc(shape[:, :1], shape[:, 1:], STEPS[None, :])
    amplitudes = np.geomspace(0.05, max_amplitude_deg * 2.0, 400)
    speed = vmax_deg_s * -np.expm1(-amplitudes / c_deg)
    duration = amplitudes * 1.875 / speed  # Beta(3, 3)'s peak rate; refined below, as the shape depends on D
    for _ in range(6):  # D = A max P' / V(A), max P' that of the main shape (SHAPES[0]) at D
        f = peak_fraction(duration)
        a, b = _beta(f, SHAPES[0][1])
        duration = amplitudes * f ** (a - 1.0) * (1.0 - f) ** (b - 1.0) / beta(a, b) / speed
    durations = np.tile(DURATIONS_S, len(SHAPES))
    return _Model(durations, np.concatenate(penalties), tables, np.log(amplitudes), np.log(duration))


@dataclass(frozen=True)
class Flight:
    """A saccade under way as the fit predicts it: the gaze at any time until it lands, and where it lands.

    The model turns start (the start point, the gaze at start_ns) about the unit axis by amplitude_deg x
    (P((t - onset_ns) / duration_ns) - P((start_ns - onset_ns) / duration_ns)), P the fitted profile's
    distribution function (tabulated; clamped to [0, 1]).
    """

    start: Vec
    axis: Vec
    start_ns: int
    onset_ns: int  # the fitted t0
    duration_ns: int
    amplitude_deg: float
    t_ns: int  # the newest sample fitted
    profile: np.ndarray = field(repr=False, compare=False)  # P at STEPS

    def displacement_deg(self, t_ns: int) -> float:
        """The model's angle from the start point at t_ns (constant once the saccade has landed)."""
        at, before = _reach(self.profile, (np.array([t_ns, self.start_ns]) - self.onset_ns) / self.duration_ns)
        return self.amplitude_deg * float(at - before)

    def gaze_at(self, t_ns: int) -> Vec:
        """The predicted unit gaze at t_ns: on the saccade's great circle, the landing point from end_ns on."""
        return turn(self.start, self.axis, math.radians(self.displacement_deg(t_ns)))

    @property
    def end_ns(self) -> int:
        """When the model lands."""
        return self.onset_ns + self.duration_ns

    @property
    def landing(self) -> Vec:
        """The predicted landing point (unit gaze)."""
        return self.gaze_at(self.end_ns)


class SaccadePredictor:
    """Saccade landing prediction for one gaze stream (the module's docstring gives the method).

    update() takes each sample in time order and returns the Flight predicted from the samples so far, or None
    when no saccade is under way or its fit is not reliable (yet); in_flight says whether a saccade is under
    way. The defaults suit 250-2000 Hz trackers. The main sequence's constants, vmax_deg_s and c_deg (V = vmax
    (1 - exp(-A / c)): 255 deg/s at 5 deg, 380 at 10, 470 at 20), were chosen to follow the peak velocities the
    EyeLink parser gave the saccades (1.5-22 deg) of the cili recordings bench/saccade_landing.py measures; the
    fit lets a person's saccades run faster or slower than them. Settings that are not positive numbers, or an
    offset above the onset, are a ValueError.
    """

    def __init__(
        self,
        onset_deg_s: float = 75.0,
        offset_deg_s: float = 40.0,
        span_ms: float = 3.0,
        noise_deg: float = 0.1,
        min_progress_deg: float = 1.0,
        max_amplitude_deg: float = 60.0,
        max_gap_ms: float = 20.0,
        max_flight_ms: float = 200.0,
        vmax_deg_s: float = 500.0,
        c_deg: float = 7.0,
    ) -> None:
        settings = dict(
            onset_deg_s=onset_deg_s,
            offset_deg_s=offset_deg_s,
            span_ms=span_ms,
            noise_deg=noise_deg,
            min_progress_deg=min_progress_deg,
            max_amplitude_deg=max_amplitude_deg,
            max_gap_ms=max_gap_ms,
            max_flight_ms=max_flight_ms,
            vmax_deg_s=vmax_deg_s,
            c_deg=c_deg,
        )
        for name, value in settings.items():
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < math.inf:
                raise ValueError(f"saccade predictor: {name} must be a positive number, got {value!r}")
        if offset_deg_s > onset_deg_s:
            raise ValueError(f"saccade predictor: offset_deg_s ({offset_deg_s}) must not exceed onset_deg_s")
        self.onset_deg_s, self.offset_deg_s = float(onset_deg_s), float(offset_deg_s)
        self.span_ns, self.max_gap_ns = round(span_ms * MS), round(max_gap_ms * MS)
        self.max_flight_ns = round(max_flight_ms * MS)
        self.noise_deg, self.min_progress_deg = float(noise_deg), float(min_progress_deg)
        self.max_amplitude_deg = float(max_amplitude_deg)
        self._model = _model(float(vmax_deg_s), float(c_deg), self.max_amplitude_deg)
        self._recent: deque[tuple[int, Vec]] = deque()  # the samples since the one span_ms before the newest
        self._speed = 0.0  # over the span to the newest sample (deg/s)
        self._start: tuple[int, Vec] | None = None  # a flight's start point; None: no flight
        self._times: list[float] = []  # the flight's samples: seconds after the start point
        self._angles: list[float] = []  # and degrees from it
        self._peak = 0.0  # the flight's highest speed
        self._fitted_ns = -FIT_INTERVAL_NS  # when the flight was last fitted
        self._flight: Flight | None = None  # and what that fit predicted
        self._settling = False  # after a turn or an over-long flight: no onset until the speed falls

    @property
    def in_flight(self) -> bool:
        """Whether a saccade is under way (its fit reliable or not)."""
        return self._start is not None

    def reset(self) -> None:
        """Forget the stream: the next sample starts afresh."""
        self._recent.clear()
        self._speed = 0.0
        self._end_flight(settle=False)

    def update(self, t_ns: int, gaze: Sequence[float] | None) -> Flight | None:
        """Take the sample at t_ns (unit head-frame gaze; None for an invalid one, e.g. in a blink) and return
        the flight predicted now, or None. Samples come in time order: one at or before the one before, or after
        a gap of more than max_gap_ms, starts afresh."""
        if gaze is None:
            self.reset()
            return None
        if self._recent and not 0 < t_ns - self._recent[-1][0] <= self.max_gap_ns:
            self.reset()
        gaze = tuple(float(c) for c in gaze)
        self._recent.append((t_ns, gaze))
        while len(self._recent) > 2 and t_ns - self._recent[1][0] >= self.span_ns:
            self._recent.popleft()
        then, before = self._recent[0]
        if t_ns - then < self.span_ns:
            return None
        step = math.degrees(angle_between(before, gaze))
        speed = step / ((t_ns - then) / S)
        rising, self._speed = speed > self._speed, speed
        if self._start is None:
            if self._settling:
                self._settling = speed >= self.offset_deg_s
                return None
            if not (speed > self.onset_deg_s and rising):
                return None
            self._start = (then, before)
            self._times, self._angles = [0.0], [0.0]
            for t, g in list(self._recent)[1:-1]:  # the samples between the start point and this one
                self._times.append((t - then) / S)
                self._angles.append(math.degrees(angle_between(before, g)))
        start_ns, start = self._start
        angle = math.degrees(angle_between(start, gaze))
        if speed < self.offset_deg_s:
            self._end_flight(settle=False)
            return None
        if angle - math.degrees(angle_between(start, before)) < 0.5 * step or t_ns - start_ns > self.max_flight_ns:
            self._end_flight(settle=True)
            return None
        self._peak = max(self._peak, speed)
        self._times.append((t_ns - start_ns) / S)
        self._angles.append(angle)
        if angle < self.min_progress_deg or speed > DECELERATED * self._peak:
            return None
        if t_ns - self._fitted_ns < FIT_INTERVAL_NS:
            return self._flight
        self._fitted_ns = t_ns
        self._flight = self._predict(t_ns, gaze, then)
        return self._flight

    def _end_flight(self, settle: bool) -> None:
        self._start = None
        self._times, self._angles = [], []
        self._peak = 0.0
        self._fitted_ns, self._flight = -FIT_INTERVAL_NS, None
        self._settling = settle

    def _predict(self, t_ns: int, gaze: Vec, then: int) -> Flight | None:
        """The flight the cheapest candidate predicts, or None when the fit is not reliable."""
        start_ns, start = self._start
        fitted = self._fit()
        if fitted is None:
            return None
        amplitude, row, onset_s = fitted
        duration_s = float(self._model.durations[row])
        profile = self._model.tables[row]
        times = (np.array([t_ns, then]) - start_ns) / S
        reach = _reach(profile, (times - onset_s) / duration_s)
        modelled = amplitude * float(reach[0] - reach[1]) / (times[0] - times[1])
        observed = (self._angles[-1] - math.degrees(angle_between(start, self._recent[0][1]))) / (times[0] - times[1])
        if abs(modelled - observed) > max(VELOCITY_DEG_S, VELOCITY_FRACTION * self._speed):
            return None
        axis = rotvec_between(start, gaze)
        norm = math.sqrt(sum(c * c for c in axis))
        return Flight(
            start=start,
            axis=tuple(c / norm for c in axis),
            start_ns=start_ns,
            onset_ns=start_ns + round(onset_s * S),
            duration_ns=round(duration_s * S),
            amplitude_deg=amplitude,
            t_ns=t_ns,
            profile=profile,
        )

    def _fit(self) -> tuple[float, int, float] | None:
        """(amplitude in degrees, the model's row, onset in seconds after the start point) of the cheapest
        candidate, or None when the candidates near it disagree or it lies on the grid's edge."""
        times, angles = np.array(self._times), np.array(self._angles)
        if len(times) > MAX_FIT_SAMPLES:
            keep = np.unique(np.linspace(0, len(times) - 1, MAX_FIT_SAMPLES).round().astype(np.intp))
            times, angles = times[keep], angles[keep]
        model = self._model
        starts = np.arange(-STARTS_BEFORE_S, times[1] + START_STEP_S / 2, START_STEP_S)
        # position[r, s, k]: sample k's time as a fraction of row r's duration after start s, in table steps
        position = np.clip((times - starts[:, None]) / model.durations[:, None, None], 0.0, 1.0) * TABLE_STEPS
        index = np.minimum(position.astype(np.intp), TABLE_STEPS - 1)
        rows = np.arange(len(model.durations))[:, None, None]
        low = model.tables[rows, index]
        profile = low + (position - index) * (model.tables[rows, index + 1] - low)
        q = profile - profile[:, :, :1]  # the model is 0 at the start point
        qq = np.einsum("rsk,rsk->rs", q, q)
        seen = qq > 1e-12  # the candidate's saccade has begun by the newest sample
        amplitude = np.einsum("rsk,k->rs", q, angles) / np.where(seen, qq, 1.0)
        amplitude = np.clip(amplitude, angles[-1], self.max_amplitude_deg * 2.0)
        residual = ((angles - amplitude[:, :, None] * q) ** 2).sum(axis=2)
        expected = np.interp(np.log(amplitude), model.log_amplitudes, model.log_durations)
        prior = ((np.log(model.durations)[:, None] - expected) / DURATION_SIGMA) ** 2 + model.penalties[:, None]
        cost = np.where(seen, residual / self.noise_deg**2 + prior, np.inf)
        best = np.unravel_index(np.argmin(cost), cost.shape)
        best_amplitude = float(amplitude[best])
        edge = best[0] % len(DURATIONS_S) in (0, len(DURATIONS_S) - 1)
        if edge or not (math.isfinite(cost[best]) and best_amplitude <= self.max_amplitude_deg):
            return None
        region = amplitude[cost <= cost[best] + COST_REGION]
        if region.max() - region.min() > 2.0 * max(AGREE_DEG, AGREE_FRACTION * best_amplitude):
            return None
        return best_amplitude, int(best[0]), float(starts[best[1]])


def predict_gazes(
    times_ns: Sequence[int], gazes: Sequence[Sequence[float] | None], horizon_ns: int, **settings: float
) -> list[Vec | None]:
    """Each sample's predicted gaze horizon_ns after it, from a SaccadePredictor fed the samples in order: the
    flight's gaze_at(t + horizon_ns) while one is predicted, else None (no saccade, or no reliable fit: the
    caller's own estimate stands). gazes are unit head-frame directions, None for invalid samples; settings go
    to SaccadePredictor. For hmdrt eval and bench/saccade_landing.py."""
    if len(times_ns) != len(gazes):
        raise ValueError(f"predict_gazes: {len(times_ns)} times but {len(gazes)} gazes")
    predictor = SaccadePredictor(**settings)
    out: list[Vec | None] = []
    for t_ns, gaze in zip(times_ns, gazes, strict=True):
        flight = predictor.update(int(t_ns), gaze)
        out.append(None if flight is None else flight.gaze_at(int(t_ns) + horizon_ns))
    return out
