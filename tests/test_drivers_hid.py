"""The DK2 codec against docs/protocols.md's vectors, the tilt fusion filter, and hid:// through a stub DK2 device."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmdrt.bus.messages import Pose
from hmdrt.drivers import open_driver
from hmdrt.drivers.base import DeviceLost
from hmdrt.drivers.emulators.dk2_stub import Dk2Stub, HeadMotion
from hmdrt.drivers.fusion import GRAVITY, OrientationFusion
from hmdrt.drivers.hid import HidAdapter, HidDriver
from hmdrt.drivers.protocols.dk2 import (
    DK2_SENSOR_SIZE,
    Dk2FormatError,
    Dk2SensorReport,
    ImuSample,
    KeepAlive,
    SensorConfig,
    decode_config,
    decode_dk1_report,
    decode_dk2_report,
    decode_keep_alive,
    decode_vector,
    encode_config,
    encode_dk2_report,
    encode_keep_alive,
    encode_vector,
)
from hmdrt.errors import ConfigError
from hmdrt.replay.trace import write_trace
from hmdrt.spatial import quat_from_yaw_pitch, quat_multiply, quat_to_matrix

from .helpers import SteppingClock

ACCEL_1G = bytes.fromhex("0000005fc4800000")
GYRO = bytes.fromhex("001f47fe0c000000")
EDGE = bytes.fromhex("fffffc00001ffffe")
DK2_REPORT = (
    bytes.fromhex("0b0000013412c40940420f00") + ACCEL_1G + GYRO + bytes(16) + bytes.fromhex("e8030cfefa00") + bytes(14)
)
DK1_REPORT = (
    bytes.fromhex("0101000100 00c409".replace(" ", "")) + ACCEL_1G + GYRO + bytes(32) + bytes.fromhex("e8030cfefa00")
)


def up_in_body(q) -> np.ndarray:
    """The world's up direction seen in the body frame: what pitch and roll determine."""
    return quat_to_matrix(q).T @ np.array([0.0, 1.0, 0.0])


def tilt_error_deg(q_true, q_est) -> float:
    return math.degrees(math.acos(float(np.clip(up_in_body(q_true) @ up_in_body(q_est), -1.0, 1.0))))


def heading_deg(q) -> float:
    forward = quat_to_matrix(q) @ np.array([0.0, 0.0, -1.0])
    return math.degrees(math.atan2(forward[0], -forward[2]))


def run_driver(driver: HidDriver, clock: SteppingClock, seconds: float) -> list[Pose]:
    poses: list[Pose] = []
    end = clock.now_ns() + int(seconds * 1e9)
    while clock.now_ns() < end:
        poses += driver.read(0.05)
    return poses


# --- codec: section 7 vectors ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "packed, values",
    [(ACCEL_1G, (0, 98066, 0)), (GYRO, (1000, -2000, 0)), (EDGE, (-1, -1048576, 1048575))],
)
def test_packed_vectors_round_trip(packed, values):
    assert decode_vector(packed) == values
    assert encode_vector(values) == packed


def test_packed_vector_rejects_out_of_range_and_wrong_size():
    with pytest.raises(Dk2FormatError, match="21-bit|integers"):
        encode_vector((0, 1 << 20, 0))
    with pytest.raises(Dk2FormatError, match="8 bytes"):
        decode_vector(ACCEL_1G[:7])


def test_dk2_report_vector_decodes_and_reencodes_byte_for_byte():
    assert len(DK2_REPORT) == DK2_SENSOR_SIZE
    r = decode_dk2_report(DK2_REPORT)
    assert (r.echo, r.num_samples, r.sample_count, r.timestamp_us) == (0, 1, 0x1234, 1_000_000)
    assert r.temperature_c == pytest.approx(25.0)
    assert r.mag == (1000, -500, 250)
    assert len(r.samples) == 1
    assert r.samples[0].accel_mps2 == pytest.approx((0.0, 9.8066, 0.0))
    assert r.samples[0].gyro_radps == pytest.approx((0.1, -0.2, 0.0))
    assert encode_dk2_report(r) == DK2_REPORT


def test_dk2_report_with_every_field_set_round_trips():
    report = Dk2SensorReport(
        echo=0xBEEF,
        num_samples=2,
        sample_count=65535,
        temperature_raw=-1234,
        timestamp_us=2**32 - 1,
        slots=(ImuSample((1, -2, 3), (-4, 5, -6)), ImuSample((-(2**20), 2**20 - 1, 0), (7, 8, 9))),
        mag=(-32768, 32767, 0),
        frame_count=513,
        frame_timestamp=123456789,
        frame_id=7,
        led_pattern_phase=3,
        exposure_count=999,
        exposure_timestamp=4321,
        reserved=0xA5A5,
    )
    data = encode_dk2_report(report)
    assert len(data) == DK2_SENSOR_SIZE
    assert decode_dk2_report(data) == report


@pytest.mark.parametrize(
    "data, message",
    [(DK2_REPORT[:63], "64 bytes, got 63"), (b"\x0c" + DK2_REPORT[1:], "id is 0x0b, got 0x0c"), (b"", "got 0")],
)
def test_dk2_report_rejects_wrong_size_or_id(data, message):
    with pytest.raises(Dk2FormatError, match=message):
        decode_dk2_report(data)


def test_dk1_report_vector_decodes():
    r = decode_dk1_report(DK1_REPORT)
    assert (r.num_samples, r.timestamp, r.last_command_id, r.temperature_raw) == (1, 256, 0, 2500)
    assert r.samples == (ImuSample((0, 98066, 0), (1000, -2000, 0)),)
    assert r.mag == (1000, -500, 250)


def test_keep_alive_and_config_reports_round_trip():
    assert encode_keep_alive(KeepAlive(10_000)) == bytes.fromhex("1100000b1027")
    assert decode_keep_alive(bytes.fromhex("1100000b1027")) == KeepAlive(10_000, 0, 0x0B)
    config = SensorConfig(flags=0x2C, packet_interval=0, sample_rate=1000, echo=5)
    assert decode_config(encode_config(config)) == config
    with pytest.raises(Dk2FormatError, match="keep-alive report is 6 bytes"):
        decode_keep_alive(bytes.fromhex("1100000b10"))
    with pytest.raises(Dk2FormatError, match="out of range"):
        encode_keep_alive(KeepAlive(70_000))


# --- fusion ---------------------------------------------------------------------------------------------------


def test_gyro_integration_follows_a_constant_turn():
    fusion = OrientationFusion(gain=0.0)
    fusion.update((0.0, 0.0, 0.0), (0.0, GRAVITY, 0.0), 0)  # aligns level
    rate = math.radians(90.0)  # 90 deg/s about +Y: a turn to the left
    for _ in range(1000):
        fusion.update((0.0, rate, 0.0), (0.0, GRAVITY, 0.0), 1_000_000)
    assert heading_deg(fusion.orientation) == pytest.approx(-90.0, abs=1e-6)


def test_accelerometer_levels_a_wrong_tilt():
    fusion = OrientationFusion(gain=2.0)
    fusion.update((0.0, 0.0, 0.0), (0.0, GRAVITY, 0.0), 0)
    fusion.orientation = tuple(quat_from_yaw_pitch(0.0, 20.0))  # believes it looks 20 deg up; it is level
    for _ in range(5000):
        fusion.update((0.0, 0.0, 0.0), (0.0, GRAVITY, 0.0), 1_000_000)
    assert tilt_error_deg((1.0, 0.0, 0.0, 0.0), fusion.orientation) < 0.01


def test_first_sample_aligns_tilt_from_gravity():
    fusion = OrientationFusion()
    q_true = quat_from_yaw_pitch(0.0, 30.0)
    fusion.update((0.0, 0.0, 0.0), tuple(up_in_body(q_true) * GRAVITY), 5_000_000)
    assert fusion.aligned
    assert tilt_error_deg(q_true, fusion.orientation) < 1e-6


def test_zero_dt_changes_nothing_and_a_stall_is_clamped_finite_and_unit():
    fusion = OrientationFusion()
    fusion.update((0.0, 0.0, 0.0), (0.0, GRAVITY, 0.0), 0)
    fusion.update((0.1, 0.2, 0.3), (0.0, GRAVITY, 0.0), 1_000_000)
    before = fusion.orientation
    assert fusion.update((5.0, -3.0, 1.0), (1.0, GRAVITY, 0.0), 0) == before
    after = fusion.update((5.0, -3.0, 1.0), (0.0, GRAVITY, 0.0), 1_000_000_000)
    assert fusion.clamped == 1
    assert all(math.isfinite(c) for c in after)
    assert math.isclose(math.fsum(c * c for c in after), 1.0, rel_tol=1e-12)
    # the clamp bounds the turn to max_dt (0.1 s) at 5.9 rad/s, not the full second
    turned = math.degrees(2 * math.acos(min(1.0, abs(float(np.dot(before, after))))))
    assert 25.0 < turned < 40.0


def test_non_finite_or_huge_samples_are_rejected_without_nan():
    fusion = OrientationFusion()
    fusion.update((0.0, 0.0, 0.0), (0.0, GRAVITY, 0.0), 0)
    before = fusion.orientation
    assert fusion.update((math.nan, 0.0, 0.0), (0.0, GRAVITY, 0.0), 1_000_000) == before
    assert fusion.update((0.0, 0.0, 0.0), (math.inf, GRAVITY, 0.0), 1_000_000) == before
    assert fusion.update((1e300, 1e300, 0.0), (0.0, GRAVITY, 0.0), 1_000_000) == before
    assert fusion.rejected == 3


# --- the stub device through the hidapi adapter ---------------------------------------------------------------


def stub_adapter(clock: SteppingClock, **kwargs) -> HidAdapter:
    motion = HeadMotion.synthetic(seed=kwargs.pop("seed", 0))
    adapter = HidAdapter(lambda: Dk2Stub(motion, clock, **kwargs))
    adapter.open(0x2833, 0x0021)
    return adapter


def drain(adapter: HidAdapter, clock: SteppingClock, until_ns: int) -> list[Dk2SensorReport]:
    reports = []
    while clock.now_ns() < until_ns:
        data = adapter.read(DK2_SENSOR_SIZE, 10)
        if data:
            reports.append(decode_dk2_report(data))
    return reports


def test_stub_streams_only_under_a_keep_alive_and_resumes_with_one():
    clock = SteppingClock()
    adapter = stub_adapter(clock)
    assert drain(adapter, clock, 100_000_000) == []  # no keep-alive yet: silent

    adapter.send_feature(encode_keep_alive(KeepAlive(timeout_ms=1000)))
    sent_at = clock.now_ns()
    first = drain(adapter, clock, sent_at + 1_500_000_000)
    assert 450 <= len(first) <= 501  # 2 ms reports for the keep-alive's one second, then silence
    t_first = [r.timestamp_us for r in first]
    assert t_first[-1] - t_first[0] <= 1_000_000
    assert all(r.num_samples == 2 and len(r.samples) == 2 for r in first)
    assert [r.sample_count for r in first] == [(first[0].sample_count + 2 * i) % 2**16 for i in range(len(first))]

    clock.advance(1_000_000_000)  # nobody reads for a second: still silent, nothing is queued
    resumed_at = clock.now_ns()
    adapter.send_feature(encode_keep_alive(KeepAlive(timeout_ms=1000)))
    resumed = drain(adapter, clock, clock.now_ns() + 500_000_000)
    assert len(resumed) >= 200
    # the stub's device clock started at 0 with the host clock: the stream resumes at the keep-alive, not before
    assert resumed_at - 2_000_000 <= resumed[0].timestamp_us * 1000 <= resumed_at + 2_000_000


def test_stub_config_report_and_bad_feature_reports():
    clock = SteppingClock()
    adapter = stub_adapter(clock)
    assert decode_config(adapter.get_feature(0x02, 7)) == SensorConfig()
    adapter.send_feature(encode_config(SensorConfig(flags=0x01, sample_rate=500)))
    assert decode_config(adapter.get_feature(0x02, 7)).sample_rate == 500
    with pytest.raises(DeviceLost, match="-1"):
        adapter.send_feature(bytes.fromhex("1100000c1027"))  # keep-alive for a report type the device lacks
    adapter.close()
    with pytest.raises(DeviceLost, match="not open"):
        adapter.read(DK2_SENSOR_SIZE, 0)


def test_stub_accelerometer_reads_gravity_plus_linear_acceleration(tmp_path):
    """A trace that accelerates at 2 m/s^2 along +X while the head pitches up 20 deg."""
    pitch_deg, a = 20.0, 2.0
    poses = [
        Pose(
            seq=i,
            t_host=i * 10_000_000,
            position=(0.5 * a * (i * 0.01) ** 2, 0.0, 0.0),
            orientation=tuple(quat_from_yaw_pitch(0.0, pitch_deg)),
        )
        for i in range(200)
    ]
    path = tmp_path / "accelerating.jsonl"
    write_trace(path, poses, device="test")
    clock = SteppingClock()
    adapter = HidAdapter(lambda: Dk2Stub(HeadMotion.from_trace(str(path)), clock, gyro_bias=0.0))
    adapter.open(0x2833, 0x0021)
    adapter.send_feature(encode_keep_alive(KeepAlive()))
    reports = drain(adapter, clock, 1_500_000_000)[50:]  # away from the trace's start
    accel = np.mean([s.accel_mps2 for r in reports for s in r.samples], axis=0)
    expected = quat_to_matrix(quat_from_yaw_pitch(0.0, pitch_deg)).T @ np.array([a, GRAVITY, 0.0])
    assert accel == pytest.approx(expected, abs=0.02)
    gyro = np.mean([s.gyro_radps for r in reports for s in r.samples], axis=0)
    assert gyro == pytest.approx((0.0, 0.0, 0.0), abs=0.001)


# --- hid:// driver ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("mag, yaw_wander_deg", [(1, 0.5), (0, None)])
def test_fused_orientation_tracks_the_stub_head_within_a_degree(mag, yaw_wander_deg):
    """Ten seconds of simulated head motion through stub -> adapter -> codec -> fusion."""
    clock = SteppingClock(5_000_000_000)
    driver = open_driver(f"hid://stub?device=dk2&seed=3&mag={mag}", clock)
    driver.open()
    poses = run_driver(driver, clock, 10.0)
    driver.close()
    assert 4900 <= len(poses) <= 5001 and all(p.valid for p in poses)
    assert driver.counters.dropped == 0 and driver.counters.malformed == 0
    truth = HeadMotion.synthetic(seed=3)
    tilt, yaw_offset = [], []
    for p in poses[::5]:
        q_true = truth.at(p.t_dev)[0]
        tilt.append(tilt_error_deg(q_true, p.orientation))
        yaw_offset.append(heading_deg(p.orientation) - heading_deg(q_true))
    assert max(tilt) < 1.0
    # yaw keeps the offset it started with (the world's yaw 0 is where the head faced when the filter
    # levelled); the magnetometer holds it there, without it yaw drifts with the 0.003 rad/s gyro bias
    wander = max(yaw_offset) - min(yaw_offset)
    assert wander < (yaw_wander_deg or 3.0)
    assert abs(np.linalg.norm(poses[-1].orientation) - 1.0) < 1e-9


def test_magnetometer_holds_yaw_against_a_gyro_bias():
    mag_body = (0.0, -0.4, -0.2)  # still and level: the body frame is the world frame
    for use_mag, bound in ((True, 0.5), (False, None)):
        fusion = OrientationFusion()
        fusion.update((0.0, 0.0, 0.0), (0.0, GRAVITY, 0.0), 0, mag_body if use_mag else None)
        for _ in range(20_000):  # 20 s at 1 kHz, 0.003 rad/s of bias about the vertical
            fusion.update((0.0, 0.003, 0.0), (0.0, GRAVITY, 0.0), 1_000_000, mag_body if use_mag else None)
        drift = abs(heading_deg(fusion.orientation))
        assert drift < bound if use_mag else drift > 3.0  # 20 s x 0.17 deg/s = 3.4 deg unchecked


def test_timestamp_wrap_maps_to_increasing_host_time():
    clock = SteppingClock(1_000_000_000)
    start_us = 2**32 - 300_000  # 0.3 s before the u32 microsecond counter wraps
    driver = HidDriver(f"hid://stub?start_us={start_us}", clock)
    driver.open()
    poses = run_driver(driver, clock, 0.8)
    t_dev = [p.t_dev for p in poses]
    t_host = [p.t_host for p in poses]
    wraps = [i for i in range(1, len(t_dev)) if t_dev[i] < t_dev[i - 1]]
    assert len(wraps) == 1 and t_dev[wraps[0] - 1] > 4.29e12 and t_dev[wraps[0]] < 1e9
    assert all(b > a for a, b in zip(t_host, t_host[1:], strict=False))
    steps = np.diff(t_host)
    assert steps[wraps[0] - 1] == pytest.approx(2_000_000, abs=1000)  # the wrap step is one report period
    assert driver.counters.dropped == 0


def test_driver_counts_samples_lost_while_not_reading():
    clock = SteppingClock()
    driver = HidDriver("hid://stub", clock)
    driver.open()
    run_driver(driver, clock, 0.2)
    clock.advance(1_000_000_000)  # the host stalls for a second; the device queues 64 reports and loses the rest
    poses = run_driver(driver, clock, 0.2)
    lost_reports = 500 - 64
    assert driver.counters.dropped == pytest.approx(2 * lost_reports, abs=4)
    assert all(math.isfinite(c) for p in poses for c in p.orientation)


def test_driver_resends_the_keep_alive_before_it_expires():
    clock = SteppingClock()
    driver = HidDriver("hid://stub?keepalive_ms=1000&bias=0&noise=0", clock)
    driver.open()
    poses = run_driver(driver, clock, 3.0)
    assert len(poses) >= 1490  # 3 s of 2 ms reports with no silent gap at the keep-alive expiries
    gaps = np.diff([p.t_dev for p in poses])
    assert gaps.max() == 2_000_000


def test_trace_driven_stub_follows_the_trace(tmp_path):
    """The head pitches up 30 degrees over two seconds, then holds."""
    poses = [
        Pose(seq=i, t_host=i * 20_000_000, position=(0.0, 0.0, 0.0), orientation=tuple(quat_from_yaw_pitch(0, p)))
        for i, p in enumerate(np.concatenate([np.linspace(0.0, 30.0, 100), np.full(50, 30.0)]))
    ]
    path = tmp_path / "pitch.jsonl"
    write_trace(path, poses, device="test")
    clock = SteppingClock()
    driver = HidDriver(f"hid://stub?trace={path}", clock)
    driver.open()
    fused = run_driver(driver, clock, 3.0)
    assert tilt_error_deg(quat_from_yaw_pitch(0.0, 30.0), fused[-1].orientation) < 1.0
    mid = next(p for p in fused if p.t_dev >= 1_000_000_000)
    assert tilt_error_deg(quat_from_yaw_pitch(0.0, 15.0), mid.orientation) < 1.0


@pytest.mark.parametrize(
    "url, message",
    [
        ("hid://stub?device=dk1", "device=dk2 only"),
        ("hid://1234:5678", "not a DK2-class tracker"),
        ("hid://2833:0021?trace=x.jsonl", "hid://stub only"),
        ("hid://rift", "VID:PID"),
        ("hid://stub?start_us=4294967296", "outside"),
    ],
)
def test_bad_hid_urls_are_clear_errors(url, message):
    with pytest.raises(ConfigError, match=message):
        open_driver(url)


def test_missing_real_device_is_a_clear_device_lost():
    driver = open_driver("hid://2833:0021")
    with pytest.raises(DeviceLost, match="no HID device 2833:0021"):
        driver.open()
    with pytest.raises(DeviceLost, match="not open"):
        driver.read(0.01)


def test_read_before_open_and_after_close_is_device_lost():
    driver = HidDriver("hid://stub", SteppingClock())
    with pytest.raises(DeviceLost):
        driver.read(0.01)
    driver.open()
    driver.close()
    driver.close()
    with pytest.raises(DeviceLost):
        driver.read(0.01)


def test_head_motion_slerps_between_knots_and_holds_after_the_last():
    """Halfway through a 40 degree turn the head has turned 20 degrees; after the last knot it holds."""
    motion = HeadMotion(
        iter([(0, np.array([1.0, 0, 0, 0]), np.zeros(3)), (10, np.array(quat_from_yaw_pitch(40, 0)), np.zeros(3))])
    )
    half = motion.at(5)[0]
    assert np.allclose(quat_multiply(half, half), quat_from_yaw_pitch(40, 0)) or np.allclose(
        quat_multiply(half, half), -np.array(quat_from_yaw_pitch(40, 0))
    )
    assert np.allclose(motion.at(20)[0], quat_from_yaw_pitch(40, 0))
