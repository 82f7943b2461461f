"""Fuzzing bytes and text from outside, HID reports (drivers.protocols.dk2, hid://):
bad input never gets in, never crashes."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st

from hmdrt.clock import VirtualClock
from hmdrt.drivers.hid import HidDriver
from hmdrt.drivers.protocols import dk2
from tests.fuzz.common import (
    fuzz,
    publishable,
)

DK2_DECODERS = [dk2.decode_dk2_report, dk2.decode_dk1_report, dk2.decode_keep_alive, dk2.decode_config]
DK2_IDS = [dk2.DK2_SENSOR_ID, dk2.DK1_SENSOR_ID, dk2.KEEP_ALIVE_ID, dk2.CONFIG_ID]


@fuzz(
    400,
    data=st.one_of(
        st.binary(max_size=80),
        st.tuples(st.sampled_from(DK2_IDS), st.sampled_from([5, 6, 7, 61, 62, 63, 64, 65])).flatmap(
            lambda t: st.binary(min_size=t[1] - 1, max_size=t[1] - 1).map(lambda b, i=t[0]: bytes([i]) + b)
        ),
    ),
)
def test_dk2_any_report_decodes_or_raises_dk2_format_error(data):
    """Every HID report decoder takes any bytes: a report of in-range fields, or Dk2FormatError."""
    for decode in DK2_DECODERS:
        try:
            report = decode(data)
        except dk2.Dk2FormatError:
            continue
        if isinstance(report, dk2.Dk2SensorReport):
            assert dk2.decode_dk2_report(dk2.encode_dk2_report(report)) == report  # every field kept
            assert dk2.encode_dk2_report(report)[:12] == data[:12] and dk2.encode_dk2_report(report)[44:] == data[44:]
            assert all(-(2**20) <= c < 2**20 for s in report.slots for c in (*s.accel, *s.gyro))
    try:
        vector = dk2.decode_vector(data)
    except dk2.Dk2FormatError:
        return
    assert dk2.encode_vector(vector)[:7] == data[:7]


DK2_REPORTS = st.one_of(
    st.binary(min_size=dk2.DK2_SENSOR_SIZE - 1, max_size=dk2.DK2_SENSOR_SIZE - 1).map(lambda b: b"\x0b" + b),
    st.binary(min_size=1, max_size=dk2.DK2_SENSOR_SIZE),  # mostly the wrong size or id
)


@fuzz(40, reports=st.lists(DK2_REPORTS, min_size=1, max_size=24))
def test_hid_driver_turns_any_report_into_a_unit_pose_or_counts_it(reports):
    """Through the real adapter and driver (hid://stub, its queue filled with arbitrary reports): each report of
    the wrong size or id raises malformed by one, each 0x0B report with samples gives one finite unit-quaternion
    pose that survives the bus decoder, and nothing escapes read() (fused IMU values at the 21-bit extremes)."""
    driver = HidDriver("hid://stub", VirtualClock(10**9))
    driver.open()
    driver.hid._queue.extend(reports)  # what the device sends next (the stub's clock stands still: nothing else)
    poses = driver.read(0.0)
    driver.close()
    sensor = [r for r in reports if len(r) == dk2.DK2_SENSOR_SIZE and r[0] == dk2.DK2_SENSOR_ID]
    assert driver.counters.malformed == len(reports) - len(sensor)
    assert len(poses) == sum(r[3] > 0 for r in sensor)  # num_samples
    for pose in poses:
        assert abs(np.linalg.norm(pose.orientation) - 1.0) < 1e-6
        publishable(pose, "hid")
