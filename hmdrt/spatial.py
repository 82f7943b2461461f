"""Poses, quaternions and gaze angles in the OpenXR convention: right-handed, +Y up, -Z forward, metres.

Quaternions are (w, x, y, z) and unit length. Gaze angles: yaw positive to the right, pitch positive up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from hmdrt.errors import ConfigError


def unit(v: ArrayLike) -> tuple[float, ...]:
    """v / |v| as a tuple of floats: for 3- and 4-vectors plain Python is several times faster than numpy."""
    v = tuple(map(float, v))
    n = math.hypot(*v)
    return tuple(c / n for c in v)


def quat_to_matrix(q: ArrayLike) -> np.ndarray:
    """Rotation matrix (3, 3) float64 of a unit quaternion (w, x, y, z)."""
    w, x, y, z = unit(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def quat_rotate(q: ArrayLike, v: ArrayLike) -> tuple[float, float, float]:
    """v rotated by the unit quaternion q (q v q*), as floats: what quat_to_matrix(q) @ v gives, without numpy."""
    w, x, y, z = unit(q)
    vx, vy, vz = map(float, v)
    tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
    return (vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz, vz + w * tz + x * ty - y * tx)


def quat_from_yaw_pitch(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Orientation that turns -Z forward by yaw (positive right) then pitch (positive up)."""
    yaw = np.radians(-yaw_deg) / 2  # a right turn is a negative rotation about +Y
    pitch = np.radians(pitch_deg) / 2
    q_yaw = np.array([np.cos(yaw), 0.0, np.sin(yaw), 0.0])
    q_pitch = np.array([np.cos(pitch), np.sin(pitch), 0.0, 0.0])
    return quat_multiply(q_yaw, q_pitch)


def quat_multiply(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Hamilton product a * b of two (w, x, y, z) quaternions."""
    aw, ax, ay, az = a
    bw, bx, by, bz = b
    return np.array(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ]
    )


def quat_conjugate(q: ArrayLike) -> np.ndarray:
    """Conjugate (w, -x, -y, -z): the inverse rotation of a unit quaternion."""
    w, x, y, z = q
    return np.array([w, -x, -y, -z], dtype=np.float64)


def quat_slerp(a: ArrayLike, b: ArrayLike, u: float) -> np.ndarray:
    """Unit quaternion a fraction u of the way from a to b along the shorter arc (u may lie outside 0..1)."""
    a, b = tuple(map(float, a)), tuple(map(float, b))
    dot = sum(p * q for p, q in zip(a, b, strict=True))
    if dot < 0.0:  # q and -q are the same rotation; take the shorter way round
        b, dot = tuple(-q for q in b), -dot
    if dot > 0.9995:
        ka, kb = 1.0 - u, u
    else:
        theta = math.acos(dot)
        ka, kb = (math.sin((1.0 - u) * theta) / math.sin(theta), math.sin(u * theta) / math.sin(theta))
    return np.array(unit([ka * p + kb * q for p, q in zip(a, b, strict=True)]))


def quat_to_rotvec(q: ArrayLike) -> np.ndarray:
    """Rotation vector (unit axis times angle in radians, angle <= pi) of a unit quaternion."""
    w, x, y, z = (float(c) for c in q)
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    scale = 2.0 * math.atan2(s, w) / s if s > 1e-12 else 2.0 / w
    return np.array([x * scale, y * scale, z * scale])


def quat_from_rotvec(v: ArrayLike) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of a rotation vector (axis times angle in radians)."""
    x, y, z = (float(c) for c in v)
    angle = math.sqrt(x * x + y * y + z * z)
    scale = math.sin(angle / 2.0) / angle if angle > 1e-12 else 0.5
    return np.array([math.cos(angle / 2.0), x * scale, y * scale, z * scale])


def gaze_direction(yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """Unit gaze direction (3,) in the head frame for yaw (right +) and pitch (up +) in degrees."""
    yaw, pitch = np.radians(yaw_deg), np.radians(pitch_deg)
    return np.array([np.sin(yaw) * np.cos(pitch), np.sin(pitch), -np.cos(yaw) * np.cos(pitch)])


def mean_direction(a: ArrayLike, b: ArrayLike) -> np.ndarray | None:
    """Unit mean (3,) float64 of two unit directions, e.g. a binocular gaze's centre; None if they cancel out."""
    mean = np.asarray(a, dtype=np.float64) + np.asarray(b, dtype=np.float64)
    norm = float(np.linalg.norm(mean))
    return mean / norm if norm > 1e-9 else None


def parse_gaze(text: str) -> tuple[float, float]:
    """Parse "YAW,PITCH" in degrees; both finite and within +-90."""
    parts = text.split(",")
    try:
        yaw, pitch = (float(p) for p in parts)
    except ValueError:
        raise ConfigError(f"gaze must be YAW,PITCH in degrees (e.g. 10,-5), got {text!r}") from None
    if not (np.isfinite(yaw) and np.isfinite(pitch) and abs(yaw) <= 90 and abs(pitch) <= 90):
        raise ConfigError(f"gaze angles must be finite and within +-90 degrees, got {text!r}")
    return yaw, pitch


@dataclass(frozen=True)
class Pose:
    """Head pose: position (m) and orientation (w, x, y, z) in world space."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    orientation: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))

    @classmethod
    def looking(cls, position, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> Pose:
        return cls(np.asarray(position, dtype=np.float64), quat_from_yaw_pitch(yaw_deg, pitch_deg))

    @classmethod
    def look_at(cls, position, target) -> Pose:
        """Pose at `position` whose -Z axis points at `target` (no roll)."""
        d = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
        yaw = np.degrees(np.arctan2(d[0], -d[2]))
        pitch = np.degrees(np.arctan2(d[1], np.hypot(d[0], d[2])))
        return cls.looking(position, yaw, pitch)

    def rotation(self) -> np.ndarray:
        return quat_to_matrix(self.orientation)
