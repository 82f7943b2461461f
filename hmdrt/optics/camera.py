"""Per-eye pinhole cameras with asymmetric frusta, and eccentricity maps.

Pixel coordinates are continuous: (0, 0) is the top-left corner of the image, pixel (i, j) has its
centre at (i + 0.5, j + 0.5), x grows right and y grows down. Eccentricity is the true angle between
a pixel's view ray and the gaze ray (weier2016 section 3.1; kim2021 section 4.1), never a pixel distance.
"""

from __future__ import annotations

import functools
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.memory import touched
from hmdrt.optics.profiles import HmdProfile
from hmdrt.spatial import Pose


class EyeRays(NamedTuple):
    """What generating an eye's view rays needs, for kernels (EyeCamera's fields, the grid as floats)."""

    tan_left: float
    tan_right: float
    tan_up: float
    tan_down: float
    width: float
    height: float
    rotation: np.ndarray  # (3, 3) float64
    position: np.ndarray  # (3,) float64


@inline
def eye_direction(eye, x, y):
    """World-space unit direction (float64 triple) of the view ray through pixel coordinates (x, y)."""
    tan_l, tan_r, tan_u, tan_d, width, height, rot, _ = eye
    tx = tan_l + x * np.divide(tan_r - tan_l, width)  # np.divide: no zero-division branch, so a loop vectorises
    ty = tan_u - y * np.divide(tan_u - tan_d, height)
    inv = np.divide(1.0, math.sqrt(tx * tx + ty * ty + 1.0))
    ex, ey, ez = tx * inv, ty * inv, -inv
    return (
        rot[0, 0] * ex + rot[0, 1] * ey + rot[0, 2] * ez,
        rot[1, 0] * ex + rot[1, 1] * ey + rot[1, 2] * ez,
        rot[2, 0] * ex + rot[2, 1] * ey + rot[2, 2] * ez,
    )


def _eye_directions(xy, eye, out):
    for i in nb.prange(xy.shape[0]):
        out[i, 0], out[i, 1], out[i, 2] = eye_direction(eye, xy[i, 0], xy[i, 1])


# starting the thread pool costs tens of microseconds, more than a few gaze samples take to convert
_eye_directions_parallel = kernel(_eye_directions)
_eye_directions_serial = serial(_eye_directions)
PARALLEL_MIN = 4096
OFF_IMAGE_TAN = 1e6  # gaze_pixel's point of regard for a gaze that never meets the image plane, in tangent units


@kernel
def _eccentricity(xy, tan_l, tan_r, tan_u, tan_d, width, height, gaze, out):
    sx = (tan_r - tan_l) / width
    sy = (tan_u - tan_d) / height
    gx, gy, gz = gaze[0], gaze[1], gaze[2]
    for i in nb.prange(xy.shape[0]):
        tx = tan_l + xy[i, 0] * sx
        ty = tan_u - xy[i, 1] * sy
        # angle between (tx, ty, -1) and the gaze: atan2(|a x g|, a.g) keeps precision near 0 and 180
        cx = ty * gz + gy
        cy = -gx - tx * gz
        cz = tx * gy - ty * gx
        dot = tx * gx + ty * gy - gz
        out[i] = math.degrees(math.atan2(math.sqrt(cx * cx + cy * cy + cz * cz), dot))


@kernel
def _pixel_centres(width, row0, rows, out):
    for r in nb.prange(rows):
        for x in range(width):
            out[r * width + x, 0] = x + 0.5
            out[r * width + x, 1] = row0 + r + 0.5


def pixel_centres(width: int, height: int, rows: slice | None = None) -> np.ndarray:
    """Pixel-centre coordinates (n, 2) float32 in scanline order, optionally for a band of rows."""
    r0, r1, _ = (rows or slice(0, height)).indices(height)
    xy = np.empty((max(r1 - r0, 0) * width, 2), dtype=np.float32)
    _pixel_centres(width, r0, max(r1 - r0, 0), xy)
    return xy


@functools.lru_cache(maxsize=64)
def _eye_frustum(profile: HmdProfile, eye: str) -> tuple[float, float, float, float, float]:
    """Tangents (left, right, up, down) of one eye's frustum and its offset from the head (m) along +X."""
    fov = profile.eye_fov(eye)
    t, r = math.tan, math.radians
    offset = (-0.5 if eye == "left" else 0.5) * profile.ipd_mm * 1e-3
    return t(r(fov.left)), t(r(fov.right)), t(r(fov.up)), t(r(fov.down)), offset


@dataclass(frozen=True)
class EyeCamera:
    """One eye: frustum tangents, pixel grid, and its world pose."""

    width: int
    height: int
    tan_left: float  # tangent of the left half-angle, negative when the frustum spans the axis
    tan_right: float
    tan_up: float
    tan_down: float  # negative when the frustum spans the axis
    position: np.ndarray  # (3,) float64, world
    rotation: np.ndarray  # (3, 3) float64, world-from-eye

    @classmethod
    def for_eye(
        cls, profile: HmdProfile, head: Pose, eye: str = "left", rotation: np.ndarray | None = None
    ) -> EyeCamera:
        """The camera of one eye of `profile` worn at head pose `head` (eye offset by IPD / 2); `rotation`:
        head.rotation() when the caller has it already (both eyes share it)."""
        rot = head.rotation() if rotation is None else rotation
        tan_left, tan_right, tan_up, tan_down, offset = _eye_frustum(profile, eye)
        position = np.asarray(head.position, dtype=np.float64) + rot[:, 0] * offset
        return cls(profile.width, profile.height, tan_left, tan_right, tan_up, tan_down, position, rot)

    def _frustum(self) -> tuple:
        return self.tan_left, self.tan_right, self.tan_up, self.tan_down, float(self.width), float(self.height)

    def directions(self, xy: np.ndarray) -> np.ndarray:
        """World-space unit view-ray directions (n, 3) float32 through pixel coordinates xy (n, 2)."""
        out = np.empty((len(xy), 3), dtype=np.float32)
        kernel = _eye_directions_parallel if len(xy) >= PARALLEL_MIN else _eye_directions_serial
        kernel(np.ascontiguousarray(xy, dtype=np.float32), self.rays(), out)
        return out

    def rays(self) -> EyeRays:
        """This eye's ray generation for kernels (eye_direction)."""
        return EyeRays(
            *self._frustum(), np.ascontiguousarray(self.rotation, np.float64), np.asarray(self.position, np.float64)
        )

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates (n, 2) and view depth along -Z (n,) of world points (n, 3); depth <= 0 is behind."""
        local = (np.asarray(points, dtype=np.float64) - self.position) @ self.rotation
        depth = -local[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            tx = local[:, 0] / depth
            ty = local[:, 1] / depth
        x = (tx - self.tan_left) / (self.tan_right - self.tan_left) * self.width
        y = (self.tan_up - ty) / (self.tan_up - self.tan_down) * self.height
        return np.stack([x, y], axis=1), depth

    def eccentricity(self, gaze: np.ndarray, xy: np.ndarray | None = None) -> np.ndarray:
        """Degrees between each view ray and the unit gaze direction (head frame).

        Returns an (height, width) map over pixel centres, or (n,) for given coordinates xy (n, 2).
        """
        pts = pixel_centres(self.width, self.height) if xy is None else np.ascontiguousarray(xy, dtype=np.float32)
        out = np.empty(len(pts), dtype=np.float32)
        _eccentricity(pts, *self._frustum(), np.asarray(gaze, dtype=np.float64), out)
        return out.reshape(self.height, self.width) if xy is None else out

    def gaze_pixel(self, gaze: np.ndarray) -> np.ndarray:
        """Continuous pixel coordinates (2,) where the gaze ray (head frame) meets the image plane.

        A gaze at or beyond 90 degrees from the view axis never meets the plane in front of the eye (at 90
        the point is at infinity, behind the eye project() would mirror it): its point of regard is put
        OFF_IMAGE_TAN tangent units from the axis in the direction the gaze leans (+x when it points straight
        back), off any image, so that what is placed around it (a foveal rectangle, weier2018's S_in) is off
        the image too. ValueError for a gaze that is not a finite, non-zero 3-vector.
        """
        g = np.asarray(gaze, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)) or not np.any(g):
            raise ValueError(f"gaze must be a finite, non-zero 3-vector (head frame), got {gaze!r}")
        side = math.hypot(g[0], g[1])
        if -g[2] * OFF_IMAGE_TAN <= side:
            tx, ty = (g[0] / side * OFF_IMAGE_TAN, g[1] / side * OFF_IMAGE_TAN) if side > 0.0 else (OFF_IMAGE_TAN, 0.0)
            x = (tx - self.tan_left) / (self.tan_right - self.tan_left) * self.width
            y = (self.tan_up - ty) / (self.tan_up - self.tan_down) * self.height
            return np.array([x, y])
        world = self.position + self.rotation @ g
        return self.project(world[None])[0][0]


class _EccentricityMaps:
    """The eccentricity maps of the last few (frustum, gaze) pairs, read-only, recomputed only on a change.

    A map depends only on the eye's frustum, its pixel grid and the head-frame gaze, not on the head pose,
    so a still gaze reuses it while the head moves. The first map of a size reserves buffers for `size` maps
    of that size (pages untouched until used) and an evicted map's buffer takes the next map of its size, so a
    moving gaze allocates nothing once running.
    """

    def __init__(self, size: int = 4):
        self._size = size
        self._maps: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._spare: dict[tuple[int, int], list[np.ndarray]] = {}
        self._lock = threading.Lock()

    def get(self, camera: EyeCamera, gaze: np.ndarray) -> np.ndarray:
        key = (camera._frustum(), float(gaze[0]), float(gaze[1]), float(gaze[2]))
        with self._lock:
            cached = self._maps.get(key)
            if cached is not None:
                self._maps.move_to_end(key)
                return cached
            shape = (camera.height, camera.width)
            if len(self._maps) >= self._size:
                _, old = self._maps.popitem(last=False)
                self._spare.setdefault(old.shape, []).append(old)
            spare = self._spare.get(shape)
            if not spare:
                spare = self._spare[shape] = list(touched((self._size, *shape)))  # first filled one by one
            out = spare.pop()
            out.flags.writeable = True
            _eccentricity(
                pixel_grid(camera.width, camera.height),
                *camera._frustum(),
                np.asarray(gaze, np.float64),
                out.reshape(-1),
            )
            out.flags.writeable = False
            self._maps[key] = out
            return out


@functools.lru_cache(maxsize=8)
def pixel_grid(width: int, height: int) -> np.ndarray:
    """pixel_centres of a whole image, shared: callers only read it. Writable, so that the kernels it is passed
    to see the same array type as their other callers' (a read-only array compiles a second specialisation)."""
    return pixel_centres(width, height)


_ECCENTRICITY_MAPS = _EccentricityMaps()


def eccentricity_map(camera: EyeCamera, gaze: np.ndarray) -> np.ndarray:
    """camera.eccentricity(gaze) as a shared read-only (height, width) map, computed once per change of the
    frustum or the gaze (weier2016 section 3.1's eccentricity of every pixel)."""
    return _ECCENTRICITY_MAPS.get(camera, gaze)
