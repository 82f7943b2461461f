"""Oculus Rift DK2 (and DK1) tracker HID reports, both ways, free of I/O (docs/protocols.md, DK2 HID and Test vectors).

Sensor reports arrive on the interrupt-IN endpoint: DK2 report 0x0B (64 bytes) carries up to two IMU
samples, a u32 microsecond timestamp (wraps about every 72 minutes) and a u16 running sample count.
Each accelerometer and gyro vector is three signed 21-bit integers packed big-endian into 8 bytes; one
unit is 1e-4 m/s^2 or 1e-4 rad/s. Feature reports 0x11 (keep-alive: the device stops streaming when
none arrives within its timeout) and 0x02 (sensor config) are encoded and decoded here as well.
Every decoder checks the report id and size and raises Dk2FormatError with a one-line reason.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

VENDOR_ID = 0x2833
PRODUCT_DK2 = (0x0021, 0x2021)  # OpenHMD accepts both (section 4.1)

DK2_SENSOR_ID = 0x0B
DK2_SENSOR_SIZE = 64
DK1_SENSOR_ID = 0x01
DK1_SENSOR_SIZE = 62
KEEP_ALIVE_ID = 0x11
KEEP_ALIVE_SIZE = 6
CONFIG_ID = 0x02
CONFIG_SIZE = 7

UNIT = 1e-4  # m/s^2 per accel count, rad/s per gyro count (section 4.2)
TIMESTAMP_WRAP_US = 2**32
SAMPLE_COUNT_WRAP = 2**16
SAMPLE_PERIOD_US = 1000  # the IMU runs at 1000 Hz; a report's later samples follow 1 ms apart

_FIELD = (1 << 21) - 1
_LOW, _HIGH = -(1 << 20), (1 << 20) - 1

_DK2_HEAD = struct.Struct("<BHBHhI")  # id, echo, num_samples, sample_count, temperature, timestamp
_DK2_TAIL = struct.Struct("<3hHIBBHHH")  # mag, frame_count, frame_ts, frame_id, led_phase, exposure_count/ts, reserved
_DK1_HEAD = struct.Struct("<BBHHh")  # id, num_samples, timestamp, last_command_id, temperature
_KEEP_ALIVE = struct.Struct("<BHBH")
_CONFIG = struct.Struct("<BHBBH")


class Dk2FormatError(ValueError):
    """A report with the wrong id, size or a field out of range."""


def _sign21(v: int) -> int:
    return v - (1 << 21) if v & (1 << 20) else v


def decode_vector(data: bytes) -> tuple[int, int, int]:
    """Three signed 21-bit integers from 8 big-endian bytes (x = bits 63..43, y = 42..22, z = 21..1)."""
    if len(data) != 8:
        raise Dk2FormatError(f"a packed vector is 8 bytes, got {len(data)}")
    bits = int.from_bytes(data, "big")
    return _sign21(bits >> 43), _sign21((bits >> 22) & _FIELD), _sign21((bits >> 1) & _FIELD)


def encode_vector(v: tuple[int, int, int]) -> bytes:
    """The 8-byte big-endian packing of three integers within the signed 21-bit range (bit 0 left 0)."""
    if len(v) != 3 or not all(isinstance(c, int) and _LOW <= c <= _HIGH for c in v):
        raise Dk2FormatError(f"a packed vector holds three integers in [{_LOW}, {_HIGH}], got {v!r}")
    x, y, z = (c & _FIELD for c in v)
    return ((x << 43) | (y << 22) | (z << 1)).to_bytes(8, "big")


@dataclass(frozen=True)
class ImuSample:
    """One raw IMU sample as sent: accel and gyro in device counts (1e-4 m/s^2, 1e-4 rad/s)."""

    accel: tuple[int, int, int]
    gyro: tuple[int, int, int]

    @property
    def accel_mps2(self) -> tuple[float, float, float]:
        return tuple(c * UNIT for c in self.accel)

    @property
    def gyro_radps(self) -> tuple[float, float, float]:
        return tuple(c * UNIT for c in self.gyro)


def _decode_samples(data: bytes, count: int) -> tuple[ImuSample, ...]:
    return tuple(
        ImuSample(decode_vector(data[16 * i : 16 * i + 8]), decode_vector(data[16 * i + 8 : 16 * i + 16]))
        for i in range(count)
    )


def _check(data: bytes, report_id: int, size: int, name: str) -> None:
    if len(data) != size:
        raise Dk2FormatError(f"{name} report is {size} bytes, got {len(data)}")
    if data[0] != report_id:
        raise Dk2FormatError(f"{name} report id is 0x{report_id:02x}, got 0x{data[0]:02x}")


@dataclass(frozen=True)
class Dk2SensorReport:
    """DK2 report 0x0B with every field as sent; `slots` are both sample slots, used or not."""

    echo: int
    num_samples: int  # samples taken since the previous report; the report carries at most two
    sample_count: int  # u16 running count of IMU samples (here: of the first sample in the report)
    temperature_raw: int  # 0.01 degC
    timestamp_us: int  # u32 device time of the first sample
    slots: tuple[ImuSample, ImuSample]
    mag: tuple[int, int, int]
    frame_count: int = 0
    frame_timestamp: int = 0
    frame_id: int = 0
    led_pattern_phase: int = 0
    exposure_count: int = 0
    exposure_timestamp: int = 0
    reserved: int = 0

    @property
    def samples(self) -> tuple[ImuSample, ...]:
        """The samples the report carries (the first min(num_samples, 2) slots)."""
        return self.slots[: min(self.num_samples, 2)]

    @property
    def temperature_c(self) -> float:
        return self.temperature_raw / 100.0


def decode_dk2_report(data: bytes) -> Dk2SensorReport:
    """Decode a 64-byte DK2 sensor report 0x0B (section 4.2)."""
    data = bytes(data)
    _check(data, DK2_SENSOR_ID, DK2_SENSOR_SIZE, "DK2 sensor")
    _, echo, num, count, temp, ts = _DK2_HEAD.unpack_from(data, 0)
    mx, my, mz, frame_count, frame_ts, frame_id, phase, exp_count, exp_ts, reserved = _DK2_TAIL.unpack_from(data, 44)
    slots = _decode_samples(data[12:44], 2)
    return Dk2SensorReport(
        echo,
        num,
        count,
        temp,
        ts,
        slots,
        (mx, my, mz),
        frame_count,
        frame_ts,
        frame_id,
        phase,
        exp_count,
        exp_ts,
        reserved,
    )


def encode_dk2_report(r: Dk2SensorReport) -> bytes:
    """The 64 bytes of a DK2 sensor report; fields out of their integer ranges raise Dk2FormatError."""
    if len(r.slots) != 2:
        raise Dk2FormatError(f"a DK2 report has two sample slots, got {len(r.slots)}")
    try:
        head = _DK2_HEAD.pack(DK2_SENSOR_ID, r.echo, r.num_samples, r.sample_count, r.temperature_raw, r.timestamp_us)
        tail = _DK2_TAIL.pack(
            *r.mag,
            r.frame_count,
            r.frame_timestamp,
            r.frame_id,
            r.led_pattern_phase,
            r.exposure_count,
            r.exposure_timestamp,
            r.reserved,
        )
    except struct.error as exc:
        raise Dk2FormatError(f"DK2 report field out of range: {exc}") from None
    body = b"".join(encode_vector(s.accel) + encode_vector(s.gyro) for s in r.slots)
    return head + body + tail


@dataclass(frozen=True)
class Dk1SensorReport:
    """DK1 report 0x01: up to three samples, a u16 timestamp of unconfirmed unit (section 10)."""

    num_samples: int
    timestamp: int
    last_command_id: int
    temperature_raw: int
    samples: tuple[ImuSample, ...]
    mag: tuple[int, int, int]


def decode_dk1_report(data: bytes) -> Dk1SensorReport:
    """Decode a 62-byte DK1 sensor report 0x01 (section 4.2); unused sample slots are skipped."""
    data = bytes(data)
    _check(data, DK1_SENSOR_ID, DK1_SENSOR_SIZE, "DK1 sensor")
    _, num, ts, cmd, temp = _DK1_HEAD.unpack_from(data, 0)
    mag = struct.unpack_from("<3h", data, 56)
    return Dk1SensorReport(num, ts, cmd, temp, _decode_samples(data[8:56], min(num, 3)), mag)


@dataclass(frozen=True)
class KeepAlive:
    """DK2 feature report 0x11: keep streaming report `report_type` for timeout_ms (section 4.3)."""

    timeout_ms: int = 10_000
    echo: int = 0
    report_type: int = DK2_SENSOR_ID


def encode_keep_alive(k: KeepAlive) -> bytes:
    try:
        return _KEEP_ALIVE.pack(KEEP_ALIVE_ID, k.echo, k.report_type, k.timeout_ms)
    except struct.error as exc:
        raise Dk2FormatError(f"keep-alive field out of range: {exc}") from None


def decode_keep_alive(data: bytes) -> KeepAlive:
    data = bytes(data)
    _check(data, KEEP_ALIVE_ID, KEEP_ALIVE_SIZE, "keep-alive")
    _, echo, report_type, timeout_ms = _KEEP_ALIVE.unpack(data)
    return KeepAlive(timeout_ms, echo, report_type)


@dataclass(frozen=True)
class SensorConfig:
    """Feature report 0x02 (section 4.3). The u16 is the sample rate to ouvrt, a keep-alive interval to OpenHMD."""

    flags: int = 0x04 | 0x08 | 0x20  # use calibration, auto calibration, command keep-alive
    packet_interval: int = 0
    sample_rate: int = 1000
    echo: int = 0


def encode_config(c: SensorConfig) -> bytes:
    try:
        return _CONFIG.pack(CONFIG_ID, c.echo, c.flags, c.packet_interval, c.sample_rate)
    except struct.error as exc:
        raise Dk2FormatError(f"sensor config field out of range: {exc}") from None


def decode_config(data: bytes) -> SensorConfig:
    data = bytes(data)
    _check(data, CONFIG_ID, CONFIG_SIZE, "sensor config")
    _, echo, flags, interval, rate = _CONFIG.unpack(data)
    return SensorConfig(flags, interval, rate, echo)
