"""The seeded synthetic gaze and head generator: rates, determinism, main-sequence saccades, pursuit,
microsaccades, blinks, vergence, tracker noise and offset, head motion."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmdrt.bus.messages import Gaze, Pose, usable
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource, minimum_jerk, saccade_duration_s
from hmdrt.spatial import quat_to_matrix


def gaze_of(config: SyntheticConfig, seconds: float) -> list[Gaze]:
    n = int(seconds * config.rate_hz)
    return [s for s in SyntheticSource(config).samples(count=n) if isinstance(s, Gaze)]


def angles(gaze: list[Gaze]) -> np.ndarray:
    """(n, 2) yaw and pitch in degrees of each sample's combined gaze."""
    c = np.array([g.C for g in gaze])
    return np.degrees(np.stack([np.arctan2(c[:, 0], -c[:, 2]), np.arcsin(np.clip(c[:, 1], -1, 1))], axis=1))


def movements(gaze: list[Gaze], rate_hz: float, threshold_deg_s: float) -> list[tuple[int, int]]:
    """[start, end) sample ranges whose gaze speed exceeds threshold_deg_s (I-VT)."""
    speed = np.hypot(*np.diff(angles(gaze), axis=0).T) * rate_hz
    fast = np.concatenate([[False], speed > threshold_deg_s, [False]])
    edges = np.flatnonzero(np.diff(fast.astype(int)))
    return list(zip(edges[::2], edges[1::2], strict=True))


@pytest.mark.parametrize("rate", [60, 120, 250, 1000])
def test_samples_come_at_the_rate_with_unit_directions_and_head_poses(rate):
    samples = list(SyntheticSource(SyntheticConfig(seed=1, rate_hz=rate)).samples(t0_ns=10**9, count=rate * 2))
    gaze = [s for s in samples if isinstance(s, Gaze)]
    poses = [s for s in samples if isinstance(s, Pose)]
    assert len(gaze) == len(poses) == rate * 2
    steps = np.diff([g.t_host for g in gaze])
    assert np.all(np.abs(steps - 1e9 / rate) <= 1) and gaze[0].t_host == 10**9
    assert [g.seq for g in gaze] == list(range(len(gaze)))
    assert all(usable(g) for g in gaze if g.valid) and all(usable(p) for p in poses)


def test_a_seed_reproduces_exactly_and_another_differs():
    a = list(SyntheticSource(SyntheticConfig(seed=4)).samples(count=500))
    b = list(SyntheticSource(SyntheticConfig(seed=4)).samples(count=500))
    c = list(SyntheticSource(SyntheticConfig(seed=5)).samples(count=500))
    assert a == b and a != c


def test_saccades_follow_the_main_sequence():
    """Without noise, each large movement lasts 21 + 2.2 A ms and peaks near 1.875 A / D (minimum jerk)."""
    rate = 1000
    gaze = gaze_of(SyntheticConfig(seed=2, rate_hz=rate, noise_deg=0.0, blink_rate_hz=0.0, pursuit_share=0.0), 20)
    a = angles(gaze)
    checked = 0
    for start, end in movements(gaze, rate, threshold_deg_s=60.0):
        amplitude = float(np.hypot(*(a[min(end + 40, len(a) - 1)] - a[max(start - 40, 0)])))
        if amplitude < 3.0:
            continue
        duration = saccade_duration_s(amplitude)
        peak = float(np.max(np.hypot(*np.diff(a[start - 1 : end + 1], axis=0).T)) * rate)
        assert peak == pytest.approx(1.875 * amplitude / duration, rel=0.05)
        # above 60 deg/s, a minimum-jerk movement spends a known share of its duration
        share = np.mean([30 * t * t * (1 - t) ** 2 > 60.0 * duration / amplitude for t in np.linspace(0, 1, 1001)])
        assert (end - start) / rate == pytest.approx(share * duration, abs=0.003)
        checked += 1
    assert checked >= 20


def test_minimum_jerk_profile():
    assert minimum_jerk(0.0) == 0.0 and minimum_jerk(1.0) == 1.0 and minimum_jerk(0.5) == pytest.approx(0.5)
    assert minimum_jerk(-1.0) == 0.0 and minimum_jerk(2.0) == 1.0


def test_pursuit_moves_smoothly_at_5_to_20_deg_per_second():
    rate = 250
    gaze = gaze_of(SyntheticConfig(seed=3, rate_hz=rate, noise_deg=0.0, blink_rate_hz=0.0, pursuit_share=1.0), 10)
    speed = np.hypot(*np.diff(angles(gaze), axis=0).T) * rate
    moving = speed[speed > 1.0]
    assert moving.size > 0.8 * speed.size  # pursuing nearly all the time
    # 5-20 deg/s, slower only where the target's path is cut short at the edge of the field
    assert 5.0 < np.median(moving) < 20.0 and np.mean(moving > 4.9) > 0.75 and np.percentile(moving, 99) < 20.5


def test_fixations_hold_with_microsaccades():
    rate = 1000
    cfg = SyntheticConfig(seed=6, rate_hz=rate, noise_deg=0.0, blink_rate_hz=0.0, pursuit_share=0.0)
    gaze = gaze_of(cfg, 30)
    small = []
    a = angles(gaze)
    for start, end in movements(gaze, rate, threshold_deg_s=5.0):
        amplitude = float(np.hypot(*(a[min(end + 2, len(a) - 1)] - a[max(start - 2, 0)])))
        if amplitude < 1.0:
            small.append((amplitude, (end - start) / rate))
    assert 10 <= len(small) <= 60  # about one every 0.8 s of fixation
    assert all(duration < 0.03 for _, duration in small)  # brief, like saccades of their size
    assert all(duration > 0.008 for amplitude, duration in small if amplitude > 0.1)  # not jumps


def test_blinks_are_invalid_runs_of_150_to_300_ms():
    rate = 250
    gaze = gaze_of(SyntheticConfig(seed=7, rate_hz=rate, blink_rate_hz=1.0), 60)
    invalid = np.array([not g.valid for g in gaze])
    edges = np.flatnonzero(np.diff(np.concatenate([[0], invalid.astype(int), [0]])))
    runs = (edges[1::2] - edges[::2]) / rate
    assert 30 <= len(runs) <= 90
    assert runs.min() >= 0.15 - 1 / rate and runs.max() <= 0.3 + 1 / rate


def test_eyes_converge_on_the_fixation_depth():
    gaze = gaze_of(SyntheticConfig(seed=8, noise_deg=0.0), 2)
    for g in gaze[::50]:
        ipd = SyntheticConfig().ipd_m
        left_eye, right_eye = np.array([-ipd / 2, 0, 0]), np.array([ipd / 2, 0, 0])
        target = np.array(g.C) * g.depth_m
        np.testing.assert_allclose(g.L, (target - left_eye) / np.linalg.norm(target - left_eye), atol=1e-9)
        np.testing.assert_allclose(g.R, (target - right_eye) / np.linalg.norm(target - right_eye), atol=1e-9)
        assert 0.5 <= g.depth_m <= 5.0


def test_tracker_offset_and_noise():
    clean = angles(gaze_of(SyntheticConfig(seed=9, noise_deg=0.0), 4))
    offset = angles(gaze_of(SyntheticConfig(seed=9, noise_deg=0.0, offset_deg=(1.5, -0.5)), 4))
    noisy = angles(gaze_of(SyntheticConfig(seed=9, noise_deg=0.3), 4))
    np.testing.assert_allclose(offset - clean, np.broadcast_to([1.5, -0.5], clean.shape), atol=1e-6)
    assert np.std(noisy - clean, axis=0) == pytest.approx([0.3, 0.3], rel=0.15)


def test_head_turns_slowly():
    rate = 250
    samples = SyntheticSource(SyntheticConfig(seed=10, rate_hz=rate)).samples(count=rate * 20)
    forward = np.array([quat_to_matrix(p.orientation) @ [0, 0, -1] for p in samples if isinstance(p, Pose)])
    yaw = np.degrees(np.arctan2(forward[:, 0], -forward[:, 2]))
    assert np.ptp(yaw) > 5.0  # it does turn
    smooth = np.convolve(yaw, np.ones(25) / 25, mode="valid")
    assert np.max(np.abs(np.diff(smooth))) * rate < 20.0  # slow turns under the jitter
    assert np.std(np.diff(yaw)) == pytest.approx(0.02 * math.sqrt(2), rel=0.5)  # jitter of 0.02 deg per sample
