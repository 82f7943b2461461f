"""A stub Rift DK2 tracker with hidapi's device methods, for hid://stub (docs/protocols.md, DK2 HID).

It synthesises what a DK2 on a moving head measures: a head trajectory (the Pose samples of a native
trace, or replay.synthetic's head motion), orientations interpolated by slerp; gyro = the body-frame
angular velocity between consecutive 1 ms samples plus a small constant bias and noise; accelerometer =
the specific force, gravity plus the trajectory's linear acceleration, rotated into the body frame, plus
noise; magnetometer = a fixed field (north along -Z, dipping down) in the body frame, plus noise, once
per report. Two samples per report, one report every 2 ms on the stub's clock (so an injected virtual clock
runs it faster than real time). Like the device it streams only while a keep-alive is in force, buffers
at most 64 reports (older ones are lost, as in hidraw's queue), and its u32 timestamp starts at start_us
and wraps.
"""

from __future__ import annotations

import bisect
import math
from collections import deque
from collections.abc import Iterator

import numpy as np

from hmdrt.bus.messages import Pose
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.fusion import GRAVITY
from hmdrt.drivers.protocols.dk2 import (
    CONFIG_ID,
    DK2_SENSOR_ID,
    KEEP_ALIVE_ID,
    PRODUCT_DK2,
    SAMPLE_COUNT_WRAP,
    SAMPLE_PERIOD_US,
    TIMESTAMP_WRAP_US,
    UNIT,
    VENDOR_ID,
    Dk2FormatError,
    Dk2SensorReport,
    ImuSample,
    SensorConfig,
    decode_config,
    decode_keep_alive,
    encode_config,
    encode_dk2_report,
)
from hmdrt.errors import ConfigError
from hmdrt.replay import load_trace
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource
from hmdrt.spatial import quat_conjugate, quat_multiply, quat_to_matrix

STUB_QUEUE = 64
REPORT_PERIOD_NS = 2 * SAMPLE_PERIOD_US * 1000


def _rotation_vector(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """The body-frame rotation vector (rad) taking orientation q0 to q1: log(q0^-1 q1) * 2."""
    d = np.array(quat_multiply(quat_conjugate(q0), q1))
    if d[0] < 0:
        d = -d
    s = math.sqrt(d[1] ** 2 + d[2] ** 2 + d[3] ** 2)
    return d[1:] * (2.0 * math.atan2(s, d[0]) / s) if s > 1e-15 else 2.0 * d[1:]


def _exp(v: np.ndarray) -> np.ndarray:
    """The unit quaternion of rotation vector v (rad)."""
    angle = float(np.linalg.norm(v))
    if angle < 1e-15:
        return np.array([1.0, *(v / 2)])
    return np.array([math.cos(angle / 2), *(v * (math.sin(angle / 2) / angle))])


class HeadMotion:
    """A head trajectory through pose knots (t_ns, orientation, position), read at increasing times.

    Orientation is interpolated by slerp, position linearly; before the first knot and after the last
    the pose holds. Knots are pulled from the iterator only as far as queries need, so an endless
    synthetic stream works.
    """

    def __init__(self, knots: Iterator[tuple[int, np.ndarray, np.ndarray]]):
        self._source = knots
        self._t: list[int] = []
        self._q: list[np.ndarray] = []
        self._p: list[np.ndarray] = []
        self._ended = False
        if not self._pull():
            raise ConfigError("a head trajectory needs at least one valid pose")

    def _pull(self) -> bool:
        for t, q, p in self._source:
            if self._t and t <= self._t[-1]:
                continue
            self._t.append(t)
            self._q.append(q / np.linalg.norm(q))
            self._p.append(p)
            return True
        self._ended = True
        return False

    def at(self, t_ns: int) -> tuple[np.ndarray, np.ndarray]:
        """(orientation (w, x, y, z), position (m)) at t_ns."""
        while not self._ended and self._t[-1] < t_ns:
            self._pull()
        if len(self._t) > 512 and self._t[256] < t_ns - 1_000_000_000:  # forget knots a second behind
            del self._t[:256], self._q[:256], self._p[:256]
        i = bisect.bisect_right(self._t, t_ns) - 1
        if i < 0:
            return self._q[0], self._p[0]
        if i >= len(self._t) - 1:
            return self._q[-1], self._p[-1]
        s = (t_ns - self._t[i]) / (self._t[i + 1] - self._t[i])
        q0, q1 = self._q[i], self._q[i + 1]
        q = np.array(quat_multiply(q0, _exp(s * _rotation_vector(q0, q1))))
        return q, self._p[i] + s * (self._p[i + 1] - self._p[i])

    @classmethod
    def synthetic(cls, seed: int) -> HeadMotion:
        """hmdrt.replay.synthetic's head motion (slow turns with jitter), knots at 100 Hz."""
        source = SyntheticSource(SyntheticConfig(seed=seed, rate_hz=100.0, head=True, blink_rate_hz=0.0))
        return cls(
            (s.t_host, np.array(s.orientation), np.array(s.position)) for s in source.samples() if isinstance(s, Pose)
        )

    @classmethod
    def from_trace(cls, path: str) -> HeadMotion:
        """The valid Pose samples of a native trace, in time order, timed from the first."""
        poses = sorted((s for s in load_trace(path).samples if isinstance(s, Pose) and s.valid), key=lambda s: s.t_host)
        poses = [p for p in poses if np.all(np.isfinite(p.orientation)) and np.linalg.norm(p.orientation) > 0.5]
        if not poses:
            raise ConfigError(f"trace {path} holds no valid pose samples to drive the hid:// stub")
        t0 = poses[0].t_host
        return cls((p.t_host - t0, np.array(p.orientation), np.array(p.position)) for p in poses)


def _counts(v: np.ndarray) -> tuple[int, int, int]:
    """SI values as device counts (1e-4 units), saturated to the 21-bit range."""
    return tuple(int(c) for c in np.clip(np.round(v / UNIT), -(2**20), 2**20 - 1))


class Dk2Stub:
    """A DK2 tracker with hidapi's device methods, its reports synthesised from a HeadMotion."""

    GRAVITY_WORLD = np.array([0.0, GRAVITY, 0.0])  # specific force at rest: up
    MAG_WORLD = np.array([0.0, -0.4, -0.2])  # gauss: north (-Z) and down
    ACCEL_SPAN_NS = 10_000_000  # linear acceleration: second difference of position over +-10 ms

    def __init__(
        self,
        motion: HeadMotion,
        clock: Clock = MONOTONIC,
        seed: int = 0,
        start_us: int = 0,
        gyro_bias: float = 0.003,
        noise: float = 1.0,
    ):
        self.motion = motion
        self.clock = clock
        self.start_us = start_us
        self._rng = np.random.default_rng([seed, 0x2833])
        direction = self._rng.normal(size=3)
        self.gyro_bias = gyro_bias * direction / np.linalg.norm(direction)
        self.gyro_noise, self.accel_noise, self.mag_noise = 0.002 * noise, 0.02 * noise, 0.005 * noise
        self.config = SensorConfig()
        self.is_open = False
        self._queue: deque[bytes] = deque(maxlen=STUB_QUEUE)
        self._t0 = 0
        self._next_report = 0
        self._keep_alive_until = -1
        self._last: tuple[int, np.ndarray] | None = None  # (sample index, orientation) of the latest sample
        self._prepared: tuple[int, bytes] | None = None  # the next report, made before it falls due

    @property
    def epoch_ns(self) -> int:
        """The host time at which the stub's (unwrapped) microsecond clock read zero."""
        return self._t0 - self.start_us * 1000

    def open(self, vendor_id: int = 0, product_id: int = 0, serial_number: str | None = None) -> None:
        if vendor_id != VENDOR_ID or product_id not in PRODUCT_DK2:
            raise OSError("open failed")
        self.open_path(b"stub:dk2")

    def open_path(self, path: bytes) -> None:
        self.is_open = True
        self._t0 = self.clock.now_ns()
        self._next_report = 0
        self._prepared = None
        self._queue.clear()

    def set_nonblocking(self, v: int) -> int:
        return 0  # the stub never blocks without a timeout

    def close(self) -> None:
        self.is_open = False

    def _check_open(self) -> None:
        if not self.is_open:
            raise ValueError("not open")

    def send_feature_report(self, data) -> int:
        self._check_open()
        data = bytes(data)
        try:
            if data[:1] == bytes([KEEP_ALIVE_ID]):
                keep_alive = decode_keep_alive(data)
                if keep_alive.report_type != DK2_SENSOR_ID:
                    return -1
                now = self.clock.now_ns()
                self._produce(now)  # reports due before now stay under the old keep-alive
                self._keep_alive_until = now + keep_alive.timeout_ms * 1_000_000
            elif data[:1] == bytes([CONFIG_ID]):
                self.config = decode_config(data)
            else:
                return -1
        except Dk2FormatError:
            return -1
        return len(data)

    def get_feature_report(self, report_num: int, max_length: int) -> list[int]:
        self._check_open()
        if report_num != CONFIG_ID:
            raise OSError("get_feature_report failed")
        return list(encode_config(self.config)[:max_length])

    def _due(self, report: int) -> int:
        """Host time at which a report is sent: when its second sample has been taken."""
        return self._t0 + report * REPORT_PERIOD_NS + REPORT_PERIOD_NS // 2

    def _sample(self, k: int) -> ImuSample:
        t = k * SAMPLE_PERIOD_US * 1000
        q, p = self.motion.at(t)
        if self._last is not None and self._last[0] == k - 1:
            q_prev = self._last[1]
        else:
            q_prev = self.motion.at(t - SAMPLE_PERIOD_US * 1000)[0]
        self._last = (k, q)
        gyro = _rotation_vector(q_prev, q) / (SAMPLE_PERIOD_US * 1e-6) + self.gyro_bias
        h = self.ACCEL_SPAN_NS
        linear = (self.motion.at(t + h)[1] - 2 * p + self.motion.at(t - h)[1]) / (h * 1e-9) ** 2
        rot = quat_to_matrix(q)
        accel = rot.T @ (linear + self.GRAVITY_WORLD)
        gyro = gyro + self._rng.normal(0.0, self.gyro_noise, 3)
        accel = accel + self._rng.normal(0.0, self.accel_noise, 3)
        return ImuSample(_counts(accel), _counts(gyro))

    def _report(self, j: int) -> bytes:
        k = 2 * j
        first, second = self._sample(k), self._sample(k + 1)
        q = self._last[1]
        return encode_dk2_report(
            Dk2SensorReport(
                echo=0,
                num_samples=2,
                sample_count=k % SAMPLE_COUNT_WRAP,
                temperature_raw=2500,
                timestamp_us=(self.start_us + k * SAMPLE_PERIOD_US) % TIMESTAMP_WRAP_US,
                slots=(first, second),
                mag=_counts(quat_to_matrix(q).T @ self.MAG_WORLD + self._rng.normal(0.0, self.mag_noise, 3)),
            )
        )

    def _prepare(self, j: int) -> bytes:
        """Report j, synthesised once (reports must be made in order: each continues the last)."""
        if self._prepared is None or self._prepared[0] != j:
            self._prepared = (j, self._report(j))
        return self._prepared[1]

    def _produce(self, now: int) -> None:
        """Queue the reports due by now that a keep-alive covers; far-behind ones are skipped (lost)."""
        behind = (now - self._due(self._next_report)) // REPORT_PERIOD_NS
        if behind > STUB_QUEUE:
            self._next_report += behind - STUB_QUEUE
        while (due := self._due(self._next_report)) <= now:
            if due <= self._keep_alive_until:
                self._queue.append(self._prepare(self._next_report))
            self._next_report += 1

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        self._check_open()
        now = self.clock.now_ns()
        self._produce(now)
        if not self._queue and timeout_ms > 0:
            wake = now + timeout_ms * 1_000_000
            due = self._due(self._next_report)
            if due <= self._keep_alive_until:
                wake = min(wake, due)
                self._prepare(self._next_report)  # ready when due, as a device's report is
            self.clock.sleep_until(wake)
            self._produce(self.clock.now_ns())
        return list(self._queue.popleft()[:max_length]) if self._queue else []
