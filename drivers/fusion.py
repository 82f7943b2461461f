"""Head orientation from IMU samples: gyro integration with accelerometer tilt and magnetometer yaw
correction (docs/protocols.md, DK2 HID).

A complementary filter in Mahony's form: the body-frame angular velocity is integrated exactly over
each step (q <- q * exp(w dt / 2)), after adding gain * (a x v), where a is the measured direction of
the specific force (up, at rest) and v the up direction the current estimate predicts, both in the
body frame. That pulls pitch and roll towards gravity with a time constant of about 1 / gain seconds
and leaves a steady tilt error of about bias / gain rad for a constant gyro bias. Yaw is not
observable from gravity; with magnetometer readings, the heading of the field's horizontal part in
the world frame is held to its mean heading over the first north_s seconds after the filter levelled
(the world's yaw 0 is where the head faced then; over so short a time the gyro drifts a fraction
of the noise of one reading), by a turn of gain * (heading error) about the up axis, so yaw no longer drifts
with the gyro bias (steady error about bias / gain rad). Without them yaw drifts, as on a DK2 without
magnetometer or camera. A magnetometer near iron needs calibrating first; that is not done here.

Accelerations far from 1 g (beyond `gate`, as a fraction of g) are not trusted for tilt, so quick head
translations do not tip the estimate. The first sample with a usable accelerometer aligns the tilt
directly (yaw starts at 0). Steps with dt <= 0 change nothing; a step longer than max_dt_ns (a stall:
the device paused or samples were lost) is clamped to max_dt_ns and counted in `clamped`, because
spreading one gyro reading over time it did not observe would invent rotation; the accelerometer then
re-levels pitch and roll. The correction is explicit: a step of dt turns by gain * dt times the error,
which overshoots past gain * dt = 1 and diverges past 2 (the explicit-integration stability limit), so
each step uses min(gain, 1 / dt), removing the error in one step at most, and counts the steps it
limited in `gain_limited`. Non-finite samples are counted in `rejected` and skipped. The quaternion
(w, x, y, z) is renormalised every step, so it never leaves the unit sphere and never becomes NaN.

Axes: the filter works in the head frame of docs/architecture.md (+X right, +Y up, +Z back); the driver hands it
samples already in that frame.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

GRAVITY = 9.80665  # m/s^2

Quat = tuple[float, float, float, float]


def _finite(*vectors: Sequence[float]) -> bool:
    return all(math.isfinite(c) for v in vectors for c in v)


class OrientationFusion:
    """Orientation (w, x, y, z) of the body (head) in a gravity-aligned world frame, +Y up."""

    def __init__(self, gain: float = 1.0, gate: float = 0.2, max_dt_ns: int = 100_000_000, north_s: float = 0.5):
        if not (math.isfinite(gain) and gain >= 0 and 0 < gate < 1 and max_dt_ns > 0):
            raise ValueError(f"fusion needs gain >= 0, 0 < gate < 1, max_dt_ns > 0; got {gain}, {gate}, {max_dt_ns}")
        self.gain = gain
        self.gate = gate
        self.max_dt_ns = max_dt_ns
        self.orientation: Quat = (1.0, 0.0, 0.0, 0.0)
        self.aligned = False
        self.north: tuple[float, float] | None = None  # the field's reference horizontal (x, z) heading
        self._north_sum = [0.0, 0.0, int(north_s * 1e9)]  # heading sum, and the time left to add to it
        self.clamped = 0
        self.rejected = 0
        self.gain_limited = 0

    def _up_direction(self, accel: Sequence[float]) -> tuple[float, float, float] | None:
        """The measured up direction (unit) if the accelerometer reads close to 1 g, else None."""
        n = math.sqrt(accel[0] ** 2 + accel[1] ** 2 + accel[2] ** 2)
        if abs(n - GRAVITY) > self.gate * GRAVITY:
            return None
        return accel[0] / n, accel[1] / n, accel[2] / n

    def _align(self, up: tuple[float, float, float]) -> None:
        """The shortest rotation taking the measured up direction to +Y: tilt from gravity, yaw 0."""
        ax, ay, az = up
        if ay < -1.0 + 1e-9:  # upside down: any half turn about a horizontal axis
            self.orientation = (0.0, 1.0, 0.0, 0.0)
        else:
            w, x, z = 1.0 + ay, -az, ax
            n = math.sqrt(w * w + x * x + z * z)
            self.orientation = (w / n, x / n, 0.0, z / n)
        self.aligned = True

    def _heading(self, mag: Sequence[float]) -> tuple[float, float] | None:
        """The unit horizontal (x, z) direction of a body-frame field in the world frame, if it has one."""
        w, x, y, z = self.orientation
        mx, my, mz = mag
        # R(q) m: the first and third rows of the rotation matrix
        hx = (1 - 2 * (y * y + z * z)) * mx + 2 * (x * y - w * z) * my + 2 * (x * z + w * y) * mz
        hz = 2 * (x * z - w * y) * mx + 2 * (y * z + w * x) * my + (1 - 2 * (x * x + y * y)) * mz
        n = math.hypot(hx, hz)
        return (hx / n, hz / n) if n > 1e-9 else None

    def _learn_north(self, heading: tuple[float, float], dt_ns: int) -> None:
        total = self._north_sum
        total[0] += heading[0]
        total[1] += heading[1]
        total[2] -= dt_ns
        n = math.hypot(total[0], total[1])
        if total[2] <= 0 and n > 1e-9:
            self.north = (total[0] / n, total[1] / n)

    def update(
        self, gyro: Sequence[float], accel: Sequence[float], dt_ns: int, mag: Sequence[float] | None = None
    ) -> Quat:
        """Fuse one sample: gyro (rad/s), accel (m/s^2) and optionally the magnetic field (any unit) in the
        head frame, dt_ns since the previous one."""
        if len(gyro) != 3 or len(accel) != 3 or not _finite(gyro, accel) or (mag is not None and not _finite(mag)):
            self.rejected += 1
            return self.orientation
        up = self._up_direction(accel)
        if not self.aligned:
            if up is not None:
                self._align(up)
            return self.orientation
        if dt_ns <= 0:
            return self.orientation
        if dt_ns > self.max_dt_ns:
            self.clamped += 1
            dt_ns = self.max_dt_ns
        dt = dt_ns * 1e-9
        gain = self.gain
        if gain * dt > 1.0:
            gain = 1.0 / dt
            self.gain_limited += 1
        w, x, y, z = self.orientation
        gx, gy, gz = gyro
        # Up direction predicted by the estimate: R^T (0, 1, 0), the second row of R(q).
        vx, vy, vz = 2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)
        if up is not None:
            ax, ay, az = up
            gx += gain * (ay * vz - az * vy)
            gy += gain * (az * vx - ax * vz)
            gz += gain * (ax * vy - ay * vx)
        heading = self._heading(mag) if mag is not None else None
        if heading is not None and self.north is None:
            self._learn_north(heading, dt_ns)
        elif heading is not None:
            # the estimate's yaw error: the signed angle about +Y from the reference heading to this one
            nx, nz = self.north
            error = math.atan2(nz * heading[0] - nx * heading[1], nx * heading[0] + nz * heading[1])
            gx, gy, gz = gx - gain * error * vx, gy - gain * error * vy, gz - gain * error * vz
        rate = math.sqrt(gx * gx + gy * gy + gz * gz)
        if not math.isfinite(rate * dt):  # rates so large the step overflows
            self.rejected += 1
            return self.orientation
        half = 0.5 * rate * dt
        s = math.sin(half) / rate if rate > 1e-12 else 0.5 * dt
        dw, dx, dy, dz = math.cos(half), gx * s, gy * s, gz * s
        q = (
            w * dw - x * dx - y * dy - z * dz,
            w * dx + x * dw + y * dz - z * dy,
            w * dy - x * dz + y * dw + z * dx,
            w * dz + x * dy - y * dx + z * dw,
        )
        n = math.sqrt(sum(c * c for c in q))
        self.orientation = (q[0] / n, q[1] / n, q[2] / n, q[3] / n)
        return self.orientation
