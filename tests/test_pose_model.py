"""The head tracker model (hmdrt.tracking.pose): each preset reproduces its published precision on a still head,
a perfect tracker reports the true pose exactly, sampling holds the true pose, and the same seed gives the same
samples."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from hmdrt.spatial import quat_conjugate, quat_from_yaw_pitch, quat_multiply, quat_to_rotvec
from hmdrt.tracking.pose import PRESETS, PoseSequence, PoseTracker, pose_tracker_named


def still_head(seconds: float, rate_hz: float = 1000.0) -> PoseSequence:
    """A head held still 1.6 m up, turned 30 deg right and 10 deg down, sampled at rate_hz."""
    t = np.arange(round(seconds * rate_hz) + 1, dtype=np.int64) * round(1e9 / rate_hz)
    position = np.tile((0.2, 1.6, -0.5), (len(t), 1))
    orientation = np.tile(quat_from_yaw_pitch(30.0, -10.0), (len(t), 1))
    return PoseSequence(t, position, orientation, np.ones(len(t), dtype=bool))


def turns_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The angle (degrees) of the rotation from each orientation of b to a's."""
    return np.degrees(
        [np.linalg.norm(quat_to_rotvec(quat_multiply(p, quat_conjugate(q)))) for p, q in zip(a, b, strict=True)]
    )


def rms(values: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(values))))


@pytest.mark.parametrize("name", list(PRESETS))
def test_each_preset_measures_its_position_and_orientation_precision_on_a_still_head(name):
    tracker = PRESETS[name]
    truth = still_head(60.0, rate_hz=1000.0)
    reported = tracker.report(truth, seed=5)
    assert reported.rate_hz == pytest.approx(min(tracker.rate_hz, 1000.0), rel=1e-6)
    if name == "perfect":
        assert np.array_equal(reported.position, truth.position)  # every true sample, as it was
        assert np.array_equal(reported.orientation, truth.orientation)
        return
    # precision as published: the RMS of the distances and angles between successive samples
    s2s_mm = np.linalg.norm(np.diff(reported.position, axis=0), axis=1) * 1e3
    assert rms(s2s_mm) == pytest.approx(tracker.position_mm, rel=0.1)
    assert rms(turns_deg(reported.orientation[1:], reported.orientation[:-1])) == pytest.approx(
        tracker.orientation_deg, rel=0.1
    )
    # white noise about the true pose, without an offset: its RMS is 1/sqrt(2) of the sample-to-sample figure
    assert np.linalg.norm(reported.position.mean(axis=0) - truth.position[0]) * 1e3 < 0.05 * tracker.position_mm
    assert rms(turns_deg(reported.orientation, truth.orientation[: len(reported.t_ns)])) == pytest.approx(
        tracker.orientation_deg / math.sqrt(2.0), rel=0.1
    )
    assert np.allclose(np.linalg.norm(reported.orientation, axis=1), 1.0)


def test_sampling_holds_the_latest_true_pose_at_multiples_of_the_period():
    t = np.arange(0, 100_000_000, 1_000_000, dtype=np.int64) + 3_000_000  # 100 ms at 1 kHz from 3 ms
    orientation = np.array([quat_from_yaw_pitch(0.1 * k, 0.0) for k in range(len(t))])  # turning 100 deg/s
    position = np.outer(np.arange(len(t)), (0.001, 0.0, 0.0))
    truth = PoseSequence(t, position, orientation, np.ones(len(t), dtype=bool))
    reported = PoseTracker(rate_hz=90.0).report(truth)
    period = round(1e9 / 90.0)
    assert reported.t_ns[0] == period and np.all(np.diff(reported.t_ns) == period)
    latest = np.searchsorted(t, reported.t_ns, side="right") - 1
    assert np.array_equal(reported.orientation, orientation[latest])
    assert np.array_equal(reported.position, position[latest])


def test_the_same_seed_gives_the_same_samples_and_invalid_samples_stay_invalid():
    truth = still_head(1.0)
    truth.valid[100:200] = False  # tracking lost in the recording
    tracker = PRESETS["htc-vive"]
    a, b, c = (tracker.report(truth, seed) for seed in ((1, 2), (1, 2), (1, 3)))
    assert np.array_equal(a.position, b.position) and np.array_equal(a.orientation, b.orientation)
    assert not np.allclose(a.orientation, c.orientation)
    lost = (a.t_ns >= truth.t_ns[100]) & (a.t_ns < truth.t_ns[200])
    assert lost.any() and not a.valid[lost].any() and a.valid[~lost].all()


def test_a_tracker_faster_than_the_true_pose_is_refused():
    with pytest.raises(ValueError, match=r"rate_hz 500 is faster than the true head pose, sampled at 250 Hz"):
        PoseTracker(rate_hz=500.0).report(still_head(0.1, rate_hz=250.0))
    with pytest.raises(ValueError, match="the true head pose has no samples"):
        PoseTracker().report(PoseSequence(*(np.zeros((0, n)) for n in (0, 3, 4)), np.zeros(0, dtype=bool)))


@pytest.mark.parametrize(
    "fields, message",
    [
        ({"position_mm": -0.1}, "Expected `float` >= 0.0 - at `$.position_mm`"),
        ({"orientation_deg": 20.0}, "Expected `float` <= 10.0 - at `$.orientation_deg`"),
        ({"rate_hz": 0.5}, "Expected `float` >= 1.0 - at `$.rate_hz`"),
        ({"drift_deg_s": 1.0}, "unknown field `drift_deg_s`"),
    ],
)
def test_bad_pose_tracker_tables_are_refused_naming_the_field(fields, message):
    with pytest.raises(msgspec.ValidationError) as err:
        msgspec.convert(fields, PoseTracker)
    assert message in str(err.value)


def test_an_unknown_pose_preset_names_the_presets_and_the_table():
    with pytest.raises(ValueError) as err:
        pose_tracker_named("quest")
    assert str(err.value) == (
        "pose_tracker 'quest' is no preset; presets: perfect, htc-vive, "
        "or a table of position_mm, orientation_deg, rate_hz"
    )
