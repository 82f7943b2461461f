"""Numerical stability at the edges, stiff dynamics: head-pose fusion, gaze and pose prediction,
fixation smoothing, clock sync."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmdrt.bus.messages import Pose
from hmdrt.compositor.samples import SampleStore
from hmdrt.drivers.clocksync import ClockSync
from hmdrt.drivers.fusion import GRAVITY, OrientationFusion
from hmdrt.foveation.stages.gaze import FixationFilter
from hmdrt.spatial import gaze_direction, quat_from_yaw_pitch
from tests.stability.common import (
    MS,
    gaze,
    yaw_of,
)

LEVEL = (0.0, GRAVITY, 0.0)


def levelled(gain: float = 1.0, **kw) -> OrientationFusion:
    fusion = OrientationFusion(gain=gain, **kw)
    fusion.update((0.0, 0.0, 0.0), LEVEL, 0)  # the first usable sample aligns the tilt
    assert fusion.orientation == (1.0, 0.0, 0.0, 0.0)
    return fusion


def tilt_error_deg(q, up) -> float:
    """Angle between the up direction the estimate predicts (R^T +Y) and the measured one."""
    w, x, y, z = q
    v = np.array([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)])
    u = np.asarray(up) / np.linalg.norm(up)
    return math.degrees(math.atan2(np.linalg.norm(np.cross(v, u)), float(v @ u)))


def test_fusion_with_dt_0_or_negative_changes_nothing():
    fusion = levelled()
    before = fusion.orientation
    for dt in (0, -1, -(10**9)):
        assert fusion.update((5.0, -3.0, 2.0), (1.0, GRAVITY, 0.0), dt) == before
    assert fusion.clamped == 0 and fusion.gain_limited == 0


def test_fusion_after_a_1_s_stall_clamps_the_step_to_max_dt_and_counts_it():
    fusion = levelled(gain=0.0, max_dt_ns=100 * MS)
    rate = math.radians(90.0)
    q = fusion.update((0.0, rate, 0.0), LEVEL, 1_000 * MS)
    half = 0.5 * rate * 0.1  # 0.1 s of rotation, not 1 s
    np.testing.assert_allclose(q, (math.cos(half), 0.0, math.sin(half), 0.0), atol=1e-15)
    assert fusion.clamped == 1


@pytest.mark.parametrize("gain_dt", [0.5, 1.0, 2.0, 2.5, 10.0, 1e6])
def test_fusion_gain_at_and_beyond_the_explicit_stability_limit_is_limited_to_one_step_and_counted(gain_dt):
    """The tilt correction turns by gain dt times the error per step: it would overshoot past gain dt = 1 and
    diverge past 2. Each step uses min(gain, 1 / dt), counted in gain_limited."""
    dt_ns = 10 * MS
    fusion = levelled(gain=gain_dt / 0.01, max_dt_ns=dt_ns)
    tilt = math.radians(20.0)
    up = (0.0, GRAVITY * math.cos(tilt), -GRAVITY * math.sin(tilt))
    errors = [tilt_error_deg(fusion.update((0.0, 0.0, 0.0), up, dt_ns), up) for _ in range(60)]
    effective = min(gain_dt, 1.0)
    # one step turns by effective * sin(error): 20 deg -> 20 - degrees(effective sin 20 deg)
    assert errors[0] == pytest.approx(20.0 - math.degrees(effective * math.sin(tilt)), abs=1e-9)
    assert all(b <= a + 1e-12 for a, b in zip(errors, errors[1:], strict=False))  # never overshoots
    assert errors[-1] < 1e-9
    assert fusion.gain_limited == (60 if gain_dt > 1.0 else 0)


def test_fusion_at_2000_deg_per_s_integrates_the_rotation_exactly():
    for gain in (0.0, 1.0):  # a level head turning about the vertical: the tilt correction has nothing to do
        fusion = levelled(gain=gain)
        rate = math.radians(2000.0)
        for _ in range(1000):
            q = fusion.update((0.0, rate, 0.0), LEVEL, MS)
        half = math.radians(2000.0) / 2  # 2000 degrees in 1 s
        np.testing.assert_allclose(np.abs(q), np.abs((math.cos(half), 0.0, math.sin(half), 0.0)), atol=1e-11)
        assert math.copysign(1, q[0] * q[2]) == math.copysign(1, math.cos(half) * math.sin(half))


def check_quaternion_norm_drift(updates: int, angle_tol: float) -> None:
    """gain 0, a constant body rate about a fixed tilted axis at 1 kHz: the closed form is one rotation."""
    fusion = levelled(gain=0.0)
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    omega = math.radians(2000.0) * axis
    gyro = tuple(omega)
    update = fusion.update
    for _ in range(updates):
        q = update(gyro, LEVEL, MS)
    assert abs(math.sqrt(sum(c * c for c in q)) - 1.0) < 1e-14
    angle = math.radians(2000.0) * updates * 1e-3
    exact = np.concatenate([[math.cos(angle / 2)], axis * math.sin(angle / 2)])
    assert min(np.linalg.norm(np.subtract(q, exact)), np.linalg.norm(np.add(q, exact))) < angle_tol


def test_fusion_quaternion_norm_does_not_drift_over_100_thousand_updates():
    check_quaternion_norm_drift(100_000, 1e-11)


def test_fusion_rejects_and_counts_non_finite_samples():
    fusion = levelled()
    before = fusion.orientation
    for gyro, accel in (((math.nan, 0, 0), LEVEL), ((0, 0, 0), (math.inf, 0, 0)), ((1e308, 1e308, 0), LEVEL)):
        assert fusion.update(gyro, accel, MS) == before
    assert fusion.rejected == 3


def test_gaze_samples_with_dt_0_between_them_give_no_velocity_and_no_division_by_zero():
    store = SampleStore()
    assert store.add("eye", gaze(0, 0, 0.0), 0) and store.add("eye", gaze(1, 0, 10.0), 0)  # same capture time
    est = store.gaze_at(5 * MS, now_ns=5 * MS)
    assert est.source_seq == 1 and yaw_of(est.left) == pytest.approx(10.0) and est.speed_deg_s == 0.0
    pose_store = SampleStore()
    for seq, yaw in ((0, 0.0), (1, 40.0)):
        q = tuple(quat_from_yaw_pitch(yaw, 0.0))
        assert pose_store.add("head", Pose(seq=seq, t_host=0, position=(0, 0, 0), orientation=q), 0)
    p = pose_store.pose_at(5 * MS, now_ns=5 * MS)
    assert np.all(np.isfinite(p.orientation)) and abs(np.linalg.norm(p.orientation) - 1) < 1e-12


def test_gaze_prediction_after_a_1_s_stall_stops_at_the_horizon_and_forgets_the_old_velocity():
    store = SampleStore(horizon_ns=50 * MS)
    for i in range(11):
        store.add("eye", gaze(i, i * MS, 0.1 * i), i * MS)  # 100 deg/s
    stalled = store.gaze_at(1010 * MS, now_ns=1000 * MS)
    assert stalled.clamped and stalled.predicted_ns == 50 * MS and stalled.age_ns == 1000 * MS
    assert yaw_of(stalled.left) == pytest.approx(1.0 + 100.0 * 0.050, abs=1e-9)  # the horizon, not 1 s of motion
    store.add("eye", gaze(11, 1000 * MS, 5.0), 1000 * MS)
    after = store.gaze_at(1010 * MS, now_ns=1000 * MS)
    assert after.speed_deg_s == 0.0 and yaw_of(after.left) == pytest.approx(5.0)  # no velocity across the stall
    across = store.gaze_at(505 * MS, now_ns=1000 * MS)  # halfway through the gap: interpolated, finite
    assert yaw_of(across.left) == pytest.approx(3.0, abs=1e-9)


def test_gaze_and_pose_at_2000_deg_per_s_are_predicted_and_interpolated_on_the_closed_form():
    store = SampleStore()
    for i in range(11):  # 2 degrees per 1 ms sample
        store.add("eye", gaze(i, i * MS, 2.0 * i), i * MS)
        q = tuple(quat_from_yaw_pitch(2.0 * i, 0.0))
        store.add("head", Pose(seq=i, t_host=i * MS, position=(0, 0, 0), orientation=q), i * MS)
    est = store.gaze_at(30 * MS, now_ns=10 * MS)
    assert yaw_of(est.left) == pytest.approx(60.0, abs=1e-9) and est.speed_deg_s == pytest.approx(2000.0)
    assert yaw_of(store.gaze_at(round(4.5 * MS), now_ns=10 * MS).left) == pytest.approx(9.0, abs=1e-9)
    pose = store.pose_at(30 * MS, now_ns=10 * MS)
    expected = quat_from_yaw_pitch(60.0, 0.0)
    assert min(np.linalg.norm(pose.orientation - expected), np.linalg.norm(pose.orientation + expected)) < 1e-12
    far = store.gaze_at(80 * MS, now_ns=10 * MS)  # 70 ms ahead: stops at the 50 ms horizon, flagged
    assert far.clamped and yaw_of(far.left) == pytest.approx(120.0, abs=1e-9)


def test_fixation_filter_alpha_1_passes_the_gaze_and_alpha_beyond_1_or_0_is_refused():
    """The EMA s <- s + alpha (g - s) is stable for 0 < alpha < 2 but overshoots above 1: the filter refuses
    alpha outside (0, 1]; alpha = 1 is the unfiltered gaze."""
    for alpha in (0.0, -0.5, 1.0 + 1e-12, 2.0, math.nan):
        with pytest.raises(ValueError, match="alpha"):
            FixationFilter(alpha)
    filt = FixationFilter(1.0, saccade_deg=3.0)
    for yaw in (0.0, 1.0, 2.5, 2.0):
        np.testing.assert_allclose(filt(gaze_direction(yaw, 0.0)), gaze_direction(yaw, 0.0), atol=1e-15)


def test_fixation_filter_counts_samples_not_time_so_a_stall_is_one_step():
    filt = FixationFilter(0.25, saccade_deg=3.0)
    filt(gaze_direction(0.0, 0.0))
    state = filt(gaze_direction(2.0, 0.0))  # after a 1 s stall or 1 ms: the same single step
    blend = 0.25 * np.array(gaze_direction(2.0, 0.0)) + 0.75 * np.array(gaze_direction(0.0, 0.0))
    np.testing.assert_allclose(state, blend / np.linalg.norm(blend), atol=1e-15)
    for _ in range(3):  # the same sample again (dt = 0 duplicates): converges, stays unit
        state = filt(gaze_direction(2.0, 0.0))
    assert abs(np.linalg.norm(state) - 1) < 1e-15 and 0.0 < yaw_of(state) < 2.0


def test_fixation_filter_with_nan_gaze_is_an_error_and_keeps_its_state():
    filt = FixationFilter(0.5)
    state = filt(gaze_direction(1.0, 0.0)).copy()
    for bad in ((math.nan, 0.0, -1.0), (math.inf, 0.0, 0.0), (0.0, 0.0, 0.0)):
        with pytest.raises(ValueError, match="finite"):
            filt(np.array(bad))
    np.testing.assert_array_equal(filt.state, state)


def test_fixation_filter_opposite_gaze_with_a_180_degree_saccade_threshold_jumps_instead_of_nan():
    filt = FixationFilter(0.5, saccade_deg=180.0)
    filt(np.array([0.0, 0.0, -1.0]))
    np.testing.assert_array_equal(filt(np.array([0.0, 0.0, 1.0])), [0.0, 0.0, 1.0])  # the blend cancels out


def test_clock_sync_with_one_sample_maps_by_its_offset_with_no_drift():
    sync = ClockSync(floor_ns=2 * MS)
    assert sync.add(1_000, 5_000_000_000) == 5_000_000_000 - 2 * MS  # capture = receive - known latency
    est = sync.estimate()
    assert est.pairs == 1 and est.drift_ppm == 0.0 and est.offset_ns == 5_000_000_000 - 1_000 - 2 * MS
    assert sync.to_host(1_000 + 7 * MS) == 5_000_000_000 - 2 * MS + 7 * MS


def test_clock_sync_with_zero_variance_latency_fits_the_exact_offset_and_no_drift():
    sync = ClockSync(floor_ns=3 * MS)
    base = 42_000_000_000
    captures = [sync.add(i * 4 * MS, base + i * 4 * MS + 3 * MS) for i in range(2_500)]  # 10 s at 250 Hz
    assert captures == [base + i * 4 * MS for i in range(2_500)]
    est = sync.estimate()
    assert est.drift_ppm == 0.0 and est.residual_ns == 0.0 and est.offset_ns == pytest.approx(base, abs=0.5)


def test_clock_sync_across_a_1_s_stall_maps_capture_times_exactly():
    """Samples stop for 1 s, then the host receives a burst 1 s late (a stalled reader) before catching up: no
    reset (the jump is within reset_ns), and every sample still maps to its true capture time."""
    latency = MS
    sync = ClockSync(floor_ns=latency)
    base = 5_000_000_000
    for i in range(3_000):  # 3 s at 1 kHz
        if 1_000 <= i < 2_000:
            continue  # the device sent nothing for 1 s
        t_dev = i * MS
        delay = 1_000 * MS if 2_000 <= i < 2_100 else 0  # the first 100 ms after it arrive 1 s late
        assert sync.add(t_dev, base + t_dev + latency + delay) == base + t_dev
    est = sync.estimate()
    assert sync.resets == 0 and est.drift_ppm == 0.0 and est.offset_ns == pytest.approx(base, abs=0.5)


def test_clock_sync_with_a_frozen_device_clock_stays_finite_with_no_slope():
    sync = ClockSync(window_ns=1, min_span_ns=0)
    out = [sync.add(5_000, 1_000_000 + k) for k in range(50)]  # the device repeats one timestamp
    assert out == [1_000_000] * 50 and sync.estimate().drift_ppm == 0.0
    # a device clock stepping back to one time after every late sample: each window's minimum sits at t_dev = 0,
    # so the minima span no device time and the least-squares slope would be 0 / 0
    sync = ClockSync(window_ns=1, min_span_ns=0)
    for k in range(40):
        if k % 2:
            sync.add((k + 1) // 2, 15_000 + 10 * k)  # late
        else:
            sync.add(0, 10_000 + 10 * k)
    est = sync.estimate()
    assert est.offset_ns == 10_000.0 and est.drift_ppm == 0.0 and sync.to_host(0) == 10_000  # the lowest minimum


def test_clock_sync_with_a_zero_or_negative_window_is_an_error():
    for kwargs in ({"window_ns": 0}, {"windows": 0}, {"reset_ns": 0}, {"min_span_ns": -1}, {"wrap_ns": 0}):
        with pytest.raises(ValueError, match="clock sync needs"):
            ClockSync(**kwargs)


def test_device_clock_jumps_of_plus_and_minus_10_s_reset_the_sync_and_are_counted():
    latency = 2 * MS
    sync = ClockSync(floor_ns=latency)
    host = 100_000_000_000
    jump = 0
    for i in range(3_000):  # 1 kHz for 3 s; the device clock jumps +10 s at 1 s and -10 s at 2 s
        if i == 1_000:
            jump = 10_000_000_000
        elif i == 2_000:
            jump = 0
        capture = host + i * MS
        assert sync.add(7 * MS + i * MS + jump, capture + latency) == capture
    assert sync.resets == 2


def test_sample_store_drops_gaze_whose_host_time_jumps_10_s_and_counts_it():
    store = SampleStore()
    for i in range(11):
        store.add("eye", gaze(i, i * MS), i * MS)
    assert not store.add("eye", gaze(11, 11 * MS + 10_000 * MS, 30.0), 11 * MS)  # 10 s ahead of its arrival
    assert not store.add("eye", gaze(12, 12 * MS - 10_000 * MS, 30.0), 12 * MS)  # 10 s behind the newest
    counts = store.counts()["eye"]
    assert (counts.ahead, counts.too_old, counts.dropped, counts.stored) == (1, 1, 2, 11)
    assert yaw_of(store.gaze_at(12 * MS, 12 * MS).left) == pytest.approx(0.0)
