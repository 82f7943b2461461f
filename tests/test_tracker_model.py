"""The tracker model (hmdrt.tracking): each preset reproduces its published accuracy and precision on a long
fixation, sampling holds the true gaze, dropouts lose what they should, and the same seed gives the same samples."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from hmdrt.spatial import gaze_direction
from hmdrt.tracking.model import FORWARD, GazeSequence, Tracker
from hmdrt.tracking.presets import PRESETS, tracker_named


def fixation(seconds: float, rate_hz: float = 1000.0, yaw: float = 10.0, pitch: float = -5.0) -> GazeSequence:
    """A still eye at (yaw, pitch), sampled at rate_hz."""
    t = np.arange(round(seconds * rate_hz) + 1, dtype=np.int64) * round(1e9 / rate_hz)
    g = np.tile(gaze_direction(yaw, pitch), (len(t), 1))
    return GazeSequence(t, g, g.copy(), np.ones(len(t), dtype=bool))


def accuracy_deg(reported: np.ndarray, true: np.ndarray) -> float:
    """The angle between the mean reported direction of a fixation and the true one."""
    mean = reported.mean(axis=0)
    return math.degrees(math.acos(min(1.0, float(mean @ true) / float(np.linalg.norm(mean)))))


def rms_s2s_deg(reported: np.ndarray) -> float:
    """Precision as trackers publish it: the RMS of the angles between successive samples."""
    cos = np.clip(np.sum(reported[1:] * reported[:-1], axis=1), -1.0, 1.0)
    return float(np.sqrt(np.mean(np.degrees(np.arccos(cos)) ** 2)))


@pytest.mark.parametrize("name", list(PRESETS))
def test_each_preset_measures_its_accuracy_and_precision_on_a_long_fixation(name):
    tracker = PRESETS[name]
    truth = fixation(20.0, rate_hz=2000.0)
    reported = tracker.report(truth, seed=11)
    assert reported.rate_hz == pytest.approx(min(tracker.rate_hz, 2000.0), rel=1e-6)
    for eye in (reported.left, reported.right):
        if name == "perfect":
            assert np.array_equal(eye, truth.left)  # every true sample, as it was
            continue
        assert accuracy_deg(eye, truth.left[0]) == pytest.approx(tracker.accuracy_deg, rel=0.1)
        assert rms_s2s_deg(eye) == pytest.approx(tracker.precision_deg, rel=0.1)


def test_the_offset_is_fixed_per_eye_in_a_seeded_direction():
    tracker = Tracker(accuracy_deg=1.0)
    truth = fixation(0.1)
    a, b, c = (tracker.report(truth, seed) for seed in (1, 1, 2))
    assert np.array_equal(a.left, b.left) and np.array_equal(a.right, b.right)  # the same seed: the same samples
    assert not np.allclose(a.left, c.left)  # another seed: another direction
    assert not np.allclose(a.left[0], a.right[0])  # each eye its own
    for eye in (a.left, a.right):
        assert np.ptp(eye, axis=0).max() < 1e-12  # fixed: no noise
        assert math.degrees(math.acos(float(eye[0] @ truth.left[0]))) == pytest.approx(1.0, abs=1e-9)


def test_sampling_holds_the_latest_true_sample_at_multiples_of_the_period():
    t = np.arange(0, 100_000_000, 1_000_000, dtype=np.int64)  # 100 ms at 1 kHz, the eye turning 100 deg/s
    g = np.array([gaze_direction(0.1 * k, 0.0) for k in range(len(t))])
    reported = Tracker(rate_hz=120.0).report(GazeSequence(t + 3_000_000, g, g, np.ones(len(t), bool)))
    period = round(1e9 / 120.0)
    assert reported.t_ns[0] == period and np.all(np.diff(reported.t_ns) == period)  # the first multiple at 3 ms on
    for when, left in zip(reported.t_ns, reported.left, strict=True):
        latest = np.searchsorted(t + 3_000_000, when, side="right") - 1
        assert np.array_equal(left, g[latest])


def test_a_tracker_faster_than_the_true_gaze_is_refused():
    with pytest.raises(ValueError, match=r"rate_hz 1000 is faster than the true gaze, sampled at 500 Hz"):
        Tracker(rate_hz=1000.0).report(fixation(0.1, rate_hz=500.0))
    Tracker(rate_hz=500.0).report(fixation(0.1, rate_hz=500.0))  # as fast is fine


def test_dropouts_lose_the_loss_rate_in_dropouts_of_loss_ms_and_blinks_stay_invalid():
    truth = fixation(600.0, rate_hz=250.0)
    truth.valid[1000:1100] = False  # a 400 ms blink
    reported = Tracker(rate_hz=250.0, loss_rate=0.05, loss_ms=40.0).report(truth, seed=3)
    assert not reported.valid[1000:1100].any()
    assert np.array_equal(reported.left[~reported.valid], np.tile(FORWARD, ((~reported.valid).sum(), 1)))
    lost = ~reported.valid
    lost[1000:1100] = False
    assert lost.mean() == pytest.approx(0.05, rel=0.15)
    runs = np.diff(np.flatnonzero(np.diff(np.concatenate([[0], lost.astype(int), [0]]))))[::2]
    assert np.median(runs) * 4.0 == pytest.approx(40.0, abs=4.0)  # samples of 4 ms


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"precision_deg": -0.1}, "Expected `float` >= 0.0 - at `$.precision_deg`"),
        ({"accuracy_deg": 45.0}, "Expected `float` <= 30.0 - at `$.accuracy_deg`"),
        ({"rate_hz": 0.0}, "Expected `float` >= 1.0 - at `$.rate_hz`"),
        ({"loss_rate": 1.0}, "Expected `float` < 1.0 - at `$.loss_rate`"),
        ({"loss_rate": 0.1}, "loss_rate 0.1 needs a dropout length: loss_ms > 0"),
        ({"noise": 1.0}, "unknown field `noise`"),
    ],
)
def test_bad_tracker_tables_are_refused_naming_the_field(fields, message):
    with pytest.raises(msgspec.ValidationError, match=None) as err:
        msgspec.convert(fields, Tracker)
    assert message in str(err.value)


def test_an_unknown_preset_names_the_presets():
    with pytest.raises(ValueError, match="tracker 'tobii' is no preset; presets: perfect, eyelink-1000-plus"):
        tracker_named("tobii")
