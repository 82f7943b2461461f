"""Poses, quaternions and gaze angles in the OpenXR convention: right-handed, +Y up, -Z forward, metres.

Quaternions are (w, x, y, z) and unit length. Gaze angles: yaw positive to the right, pitch positive up.
Vectors and quaternions come back as tuples of floats, whatever they were given as: on the per-sample paths
plain Python is several times faster than numpy for 3- and 4-vectors. Callers that need arrays wrap them with
np.asarray; a rotation matrix is a (3, 3) array, and Pose holds float64 arrays for the renderer.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from hmdrt.errors import ConfigError

Vec = tuple[float, ...]
Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def unit(v: ArrayLike) -> Vec:
    """v / |v|."""
    v = tuple(map(float, v))
    n = math.hypot(*v)
    return tuple(c / n for c in v)


def norm(v: Sequence[float]) -> float:
    """|v|."""
    return math.hypot(*v)


def dot(a: Sequence[float], b: Sequence[float]) -> float:
    """a . b of 3-vectors."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def cross(a: Sequence[float], b: Sequence[float]) -> Vec3:
    """a x b of 3-vectors."""
    ax, ay, az = a
    bx, by, bz = b
    return (ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx)


def sub(a: Sequence[float], b: Sequence[float]) -> Vec:
    """a - b."""
    return tuple(x - y for x, y in zip(a, b, strict=True))


def advance(p: Sequence[float], v: Sequence[float], h: float) -> Vec:
    """p + h v: a point moved for h seconds at velocity v."""
    return tuple(x + h * y for x, y in zip(p, v, strict=True))


def lerp(a: Sequence[float], b: Sequence[float], u: float) -> Vec:
    """The point a fraction u of the way from a to b (u may lie outside 0..1)."""
    return tuple(x + u * (y - x) for x, y in zip(a, b, strict=True))


def nlerp(a: Sequence[float], b: Sequence[float], u: float) -> Vec:
    """Unit direction a fraction u of the way from unit a to unit b; the nearer end where they cancel out."""
    v = lerp(a, b, u)
    n = norm(v)
    return tuple(c / n for c in v) if n > 1e-12 else tuple(a if u < 0.5 else b)


def angle_between(a: Sequence[float], b: Sequence[float]) -> float:
    """Angle in radians between unit directions a and b."""
    return math.atan2(norm(cross(a, b)), dot(a, b))


def rotvec_between(a: Sequence[float], b: Sequence[float]) -> Vec3:
    """Rotation vector (axis times radians) of the shortest rotation turning unit direction a into b."""
    c = cross(a, b)
    s = norm(c)
    if s <= 1e-15:
        return (0.0, 0.0, 0.0)
    k = math.atan2(s, dot(a, b)) / s
    return tuple(x * k for x in c)


def turn(d: Sequence[float], spin: Sequence[float], h: float) -> Vec:
    """Unit direction d turned for h seconds at angular velocity spin (rad/s rotation vector; Rodrigues)."""
    rate = norm(spin)
    if rate * h < 1e-15:
        return tuple(d)
    k = tuple(c / rate for c in spin)
    cos, sin = math.cos(rate * h), math.sin(rate * h)
    along = dot(k, d) * (1.0 - cos)
    return unit(tuple(x * cos + y * sin + z * along for x, y, z in zip(d, cross(k, d), k, strict=True)))


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


def quat_rotate(q: ArrayLike, v: ArrayLike) -> Vec3:
    """v rotated by the unit quaternion q (q v q*): what quat_to_matrix(q) @ v gives, without numpy."""
    w, x, y, z = unit(q)
    vx, vy, vz = map(float, v)
    tx, ty, tz = 2.0 * (y * vz - z * vy), 2.0 * (z * vx - x * vz), 2.0 * (x * vy - y * vx)
    return (vx + w * tx + y * tz - z * ty, vy + w * ty + z * tx - x * tz, vz + w * tz + x * ty - y * tx)


def quat_from_yaw_pitch(yaw_deg: float, pitch_deg: float) -> Quat:
    """Orientation that turns -Z forward by yaw (positive right) then pitch (positive up)."""
    yaw = math.radians(-yaw_deg) / 2  # a right turn is a negative rotation about +Y
    pitch = math.radians(pitch_deg) / 2
    return quat_multiply((math.cos(yaw), 0.0, math.sin(yaw), 0.0), (math.cos(pitch), math.sin(pitch), 0.0, 0.0))


def quat_multiply(a: ArrayLike, b: ArrayLike) -> Quat:
    """Hamilton product a * b of two (w, x, y, z) quaternions."""
    aw, ax, ay, az = map(float, a)
    bw, bx, by, bz = map(float, b)
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_conjugate(q: ArrayLike) -> Quat:
    """Conjugate (w, -x, -y, -z): the inverse rotation of a unit quaternion."""
    w, x, y, z = map(float, q)
    return (w, -x, -y, -z)


def quat_slerp(a: ArrayLike, b: ArrayLike, u: float) -> Vec:
    """Unit quaternion a fraction u of the way from a to b along the shorter arc (u may lie outside 0..1)."""
    a, b = tuple(map(float, a)), tuple(map(float, b))
    cos = sum(p * q for p, q in zip(a, b, strict=True))
    if cos < 0.0:  # q and -q are the same rotation; take the shorter way round
        b, cos = tuple(-q for q in b), -cos
    if cos > 0.9995:
        ka, kb = 1.0 - u, u
    else:
        theta = math.acos(cos)
        ka, kb = (math.sin((1.0 - u) * theta) / math.sin(theta), math.sin(u * theta) / math.sin(theta))
    return unit([ka * p + kb * q for p, q in zip(a, b, strict=True)])


def quat_to_rotvec(q: ArrayLike) -> Vec3:
    """Rotation vector (unit axis times angle in radians, angle <= pi) of a unit quaternion."""
    w, x, y, z = map(float, q)
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = math.sqrt(x * x + y * y + z * z)
    scale = 2.0 * math.atan2(s, w) / s if s > 1e-12 else 2.0 / w
    return (x * scale, y * scale, z * scale)


def quat_from_rotvec(v: ArrayLike) -> Quat:
    """Unit quaternion (w, x, y, z) of a rotation vector (axis times angle in radians)."""
    x, y, z = map(float, v)
    angle = math.sqrt(x * x + y * y + z * z)
    scale = math.sin(angle / 2.0) / angle if angle > 1e-12 else 0.5
    return (math.cos(angle / 2.0), x * scale, y * scale, z * scale)


def gaze_direction(yaw_deg: float, pitch_deg: float) -> Vec3:
    """Unit gaze direction in the head frame for yaw (right +) and pitch (up +) in degrees."""
    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    return (math.sin(yaw) * math.cos(pitch), math.sin(pitch), -math.cos(yaw) * math.cos(pitch))


def gaze_angles(direction: Sequence[float]) -> tuple[float, float]:
    """(yaw, pitch) in degrees of a head-frame gaze direction: the inverse of gaze_direction for yaw within +-180."""
    x, y, z = direction
    return math.degrees(math.atan2(x, -z)), math.degrees(math.atan2(y, math.hypot(x, z)))


def mean_direction(a: ArrayLike, b: ArrayLike) -> Vec | None:
    """Unit mean of two unit directions, e.g. a binocular gaze's centre; None if they cancel out."""
    mean = tuple(float(p) + float(q) for p, q in zip(a, b, strict=True))
    n = norm(mean)
    return tuple(c / n for c in mean) if n > 1e-9 else None


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
    """Head pose: position (m) and orientation (w, x, y, z) in world space, as float64 arrays whatever they
    were given as (the renderer does array arithmetic on them)."""

    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    orientation: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", np.asarray(self.position, dtype=np.float64))
        object.__setattr__(self, "orientation", np.asarray(self.orientation, dtype=np.float64))

    @classmethod
    def looking(cls, position, yaw_deg: float = 0.0, pitch_deg: float = 0.0) -> Pose:
        return cls(position, quat_from_yaw_pitch(yaw_deg, pitch_deg))

    @classmethod
    def look_at(cls, position, target) -> Pose:
        """Pose at `position` whose -Z axis points at `target` (no roll)."""
        d = np.asarray(target, dtype=np.float64) - np.asarray(position, dtype=np.float64)
        yaw = np.degrees(np.arctan2(d[0], -d[2]))
        pitch = np.degrees(np.arctan2(d[1], np.hypot(d[0], d[2])))
        return cls.looking(position, yaw, pitch)

    def rotation(self) -> np.ndarray:
        return quat_to_matrix(self.orientation)
