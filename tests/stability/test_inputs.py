"""Numerical stability at the edges: inputs: bad gaze, blinks, disorder, rates, sizes, empty scenes."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from hmdrt.bus.messages import Gaze
from hmdrt.compositor.samples import SampleStore
from hmdrt.errors import ConfigError
from hmdrt.foveation import METHODS, FrameRequest
from hmdrt.optics import get_profile
from hmdrt.optics.profiles import HmdProfile
from hmdrt.scene import load_scene
from hmdrt.spatial import gaze_direction, parse_gaze
from tests.stability.common import (
    FORWARD,
    MS,
    SKY,
    camera,
    empty_scene,
    gaze,
    render_frames,
    yaw_of,
)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nan_or_infinite_gaze_is_dropped_and_counted_by_the_store_and_refused_by_the_renderer(bad):
    store = SampleStore()
    store.add("eye", gaze(0, 0, 3.0), 0)
    for seq, fields in enumerate(({"C": (bad, 0.0, -1.0)}, {"L": (0.0, bad, -1.0)}, {"R": (0.0, 0.0, bad)}), 1):
        assert not store.add("eye", Gaze(seq=seq, t_host=seq * MS, **fields), seq * MS)
    assert not store.add("eye", Gaze(seq=9, t_host=9 * MS, C=(0.0, 0.0, -1.0), depth_m=bad), 9 * MS)
    counts = store.counts()["eye"]
    assert counts.malformed == 4 and counts.stored == 1
    assert yaw_of(store.gaze_at(10 * MS, 10 * MS).left) == pytest.approx(3.0)
    cam = camera(8, 8)
    with pytest.raises(ValueError, match="finite"):
        FrameRequest(cam, np.array([bad, 0.0, -1.0]))
    with pytest.raises(ValueError, match="finite"):
        cam.gaze_pixel(np.array([0.0, bad, -1.0]))
    with pytest.raises(ConfigError, match="finite"):
        parse_gaze(f"{bad},0")


def test_a_half_second_blink_holds_the_last_gaze_and_a_half_second_gap_stops_prediction_at_the_horizon():
    store = SampleStore(horizon_ns=50 * MS)
    for i in range(101):
        store.add("eye", gaze(i, i * MS, 0.05 * i), i * MS)  # 50 deg/s up to 100 ms
    for i in range(101, 601):
        store.add("eye", gaze(i, i * MS, valid=False), i * MS)  # eyes closed for 0.5 s
    during = store.gaze_at(400 * MS, now_ns=400 * MS)
    assert during.blinking and during.blink_since_ns == 101 * MS and during.predicted_ns == 0
    assert yaw_of(during.left) == pytest.approx(5.0, abs=1e-9)  # held, not extrapolated 0.3 s at 50 deg/s
    for i in range(601, 611):
        store.add("eye", gaze(i, i * MS, 8.0), i * MS)
    after = store.gaze_at(620 * MS, now_ns=610 * MS)
    assert not after.blinking and after.speed_deg_s == 0.0 and yaw_of(after.left) == pytest.approx(8.0)
    gap = store.gaze_at(1110 * MS, now_ns=1110 * MS)  # no samples at all for 0.5 s
    assert gap.clamped and gap.predicted_ns == 50 * MS and yaw_of(gap.left) == pytest.approx(8.0)
    assert store.counts()["eye"].invalid == 500


def test_gaze_out_of_order_and_duplicated_gives_the_same_estimates_as_in_order_and_is_counted():
    rng = np.random.default_rng(4)
    samples = [gaze(i, i * MS, 20.0 * math.sin(i / 40.0)) for i in range(200)]
    received = {s.seq: (s.seq // 10 + 1) * 10 * MS for s in samples}  # bursts of 10, delivered at the burst's end
    ordered, shuffled = SampleStore(), SampleStore()
    for s in samples:
        ordered.add("eye", s, received[s.seq])
    arrivals = []
    for burst in range(20):
        chunk = samples[burst * 10 : burst * 10 + 10]
        arrivals += [chunk[i] for i in rng.permutation(10)]
    duplicates = [samples[i] for i in rng.choice(200, 25, replace=False)]
    for s in arrivals + duplicates:
        shuffled.add("eye", s, received[s.seq])
    counts = shuffled.counts()["eye"]
    assert counts.duplicates == 25 and counts.out_of_order > 0 and counts.stored == 200
    for t, now in ((5 * MS, 10 * MS), (55 * MS, 60 * MS), (125 * MS, 130 * MS), (230 * MS, 200 * MS)):
        a, b = ordered.gaze_at(t, now), shuffled.gaze_at(t, now)
        np.testing.assert_array_equal(a.left, b.left)
        assert (a.source_seq, a.predicted_ns) == (b.source_seq, b.predicted_ns)


def test_1_khz_gaze_into_a_60_hz_compositor_tracks_the_closed_form_within_the_prediction_error():
    """A sinusoidal saccade-free gaze (yaw = 10 sin(2 pi 2 t)) at 1 kHz, 2 ms transport latency; each 60 Hz frame
    asks for the gaze 20 ms ahead, h <= 23 ms past the newest sample that has arrived. The velocity fitted over
    3 samples 1 ms apart is the slope 0.9 ms back, so the error is at most |yaw''| (h^2 / 2 + 0.9 ms h) = 0.45 deg."""

    def yaw_at(t_ns: int) -> float:
        return 10.0 * math.sin(2 * math.pi * 2.0 * t_ns * 1e-9)

    store = SampleStore()
    for i in range(1001):
        store.add("eye", gaze(i, i * MS, yaw_at(i * MS)), i * MS + 2 * MS)
    errors = []
    for frame in range(1, 60):
        now = round(frame * 1e9 / 60)
        est = store.gaze_at(now + 20 * MS, now)
        assert est.source_t_host <= now - 2 * MS  # only samples that had arrived
        errors.append(abs(yaw_of(est.left) - yaw_at(now + 20 * MS)))
    h = 0.023
    assert max(errors) <= 10.0 * (4 * math.pi) ** 2 * (h * h / 2 + 0.0009 * h)
    assert max(errors) > 0.3  # the bound is close: it is a prediction, not a lookup of the future
    counts = store.counts()["eye"]
    assert counts.samples == 1001 and counts.dropped == 0


def test_zero_size_profiles_are_an_error(tmp_path):
    profile = get_profile("sim-cpu")
    for w, h in ((0, 16), (16, 0), (0, 0), (-1, 4)):
        with pytest.raises(ConfigError, match="at least 1x1"):
            profile.with_resolution(w, h)
    with pytest.raises(ConfigError, match="at least 1x1"):
        profile.with_resolution_text("0x720")
    with pytest.raises(msgspec.ValidationError):
        msgspec.convert(
            {
                "name": "z",
                "width": 0,
                "height": 1,
                "fov": {"left": -40, "right": 40, "up": 40, "down": -40},
                "refresh_hz": 60,
            },
            HmdProfile,
        )
    path = tmp_path / "zero.toml"
    fov = "[fov]\nleft = -40.0\nright = 40.0\nup = 40.0\ndown = -40.0\n"
    path.write_text(f'name = "z"\nwidth = 0\nheight = 10\nrefresh_hz = 60.0\n{fov}')
    with pytest.raises(ConfigError, match="width"):
        get_profile(str(path))


def test_a_1x1_profile_renders_the_centre_ray_finitely_with_every_method():
    scene = load_scene("whitted")
    reference, _ = render_frames(scene, "full", [FORWARD], 1, 1)
    for method in METHODS:
        images, _ = render_frames(scene, method, [FORWARD] * 3, 1, 1)
        for im in images:
            assert im.shape == (1, 1, 3) and np.all(np.isfinite(im)) and np.all(im >= 0), method
        if method != "regular":  # regular averages 36 jittered samples over the whole (90 degree) pixel
            np.testing.assert_allclose(images[-1], reference[0], rtol=1e-5, atol=1e-6, err_msg=method)


def test_an_empty_scene_renders_the_background_with_every_method():
    # 12 frames: one refresh cycle of rrm's persistent buffer
    gazes = [FORWARD, np.array(gaze_direction(10.0, 5.0))] * 6
    for method in METHODS:
        images, stats = render_frames(empty_scene(), method, gazes)
        for im in images if method != "rrm" else images[-1:]:
            np.testing.assert_allclose(im, np.broadcast_to(SKY, im.shape), rtol=1e-6, err_msg=method)
        assert stats[-1].rays["shadow"] == 0 and stats[-1].rays["secondary"] == 0
