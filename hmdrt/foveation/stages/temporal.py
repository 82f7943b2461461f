"""Combining frames over time.

weier2016 section 3.4: the running estimate with alpha' = 1 / (rho + 1), rho the accumulated sample
count, and the age-dependent lower bound k(dt) between k_min and k_max over t_max frames.
kim2021 section 4.7: exponential smoothing over up to four back-projected earlier frames, in closed
form, with an eccentricity-dependent blending factor alpha(e). Both keep per-eye history.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from hmdrt.foveation.stages.reproject import (
    CameraArrays,
    bilinear3,
    camera_arrays,
    nearest_index,
    project,
    world_point,
)
from hmdrt.optics.camera import EyeCamera


@nb.njit(cache=True, nogil=True, inline="always")
def k_of_age(dt, k_min, k_max, t_max):
    """weier2016's k_t(dt) = min(exp(x0 + (dt - 1) / (t_max - 1) (x1 - x0)), k_max), x0 = ln k_min, x1 = ln k_max.

    t_max = 1 leaves no room to grow (the formula divides by zero there): k is k_max for every dt >= 1.
    Ages count frames from 1 (a sample one frame old); a younger one (dt < 1: the same frame number again,
    or frames numbered afresh) takes k_min, where the formula would fall below the bound.
    """
    if t_max <= 1.0:
        return k_max
    dt = max(dt, 1.0)
    x0, x1 = math.log(k_min), math.log(k_max)
    return min(math.exp(x0 + (dt - 1.0) / (t_max - 1.0) * (x1 - x0)), k_max)


@nb.njit(cache=True, nogil=True, inline="always")
def running_estimate(rho_prev, k):
    """weier2016 equation (1)'s blending weight and the new accumulated count, given the count so far.

    alpha' = 1 / (rho_{t-1} + 1); alpha = max(alpha', k); rho_t = (alpha^2 + (1 - alpha)^2 / rho_{t-1})^-1.
    The paper prints min(alpha', k) but defines k as "the minimum possible weight for the new sample"
    that grows with age; only max makes it a lower bound, so max is implemented.
    The limits are kept: nothing accumulated (rho_{t-1} <= 0, the limit rho -> 0) gives alpha = rho = 1, and
    alpha = 0 with rho_{t-1} = inf (k = 0) gives rho = inf, where the formula would divide by zero.
    """
    if rho_prev <= 0.0:
        return 1.0, 1.0
    alpha = max(1.0 / (rho_prev + 1.0), k)
    den = alpha * alpha + (1.0 - alpha) * (1.0 - alpha) / rho_prev
    return alpha, (1.0 / den if den > 0.0 else math.inf)


class History:
    """The last `size` frames of one eye in preallocated rings: camera, hit distance (inf on a miss)
    and colour. A change of image size starts the history afresh."""

    def __init__(self, size: int):
        self.size = size
        self.cameras: list[EyeCamera | None] = [None] * size
        self.depth: np.ndarray | None = None  # (size, h, w) float32
        self.color: np.ndarray | None = None  # (size, h, w, 3) float32
        self._newest = -1
        self._count = 0

    def push(self, camera: EyeCamera, depth: np.ndarray, color: np.ndarray) -> None:
        if self.depth is None or self.depth.shape[1:] != depth.shape:
            self.depth = np.empty((self.size, *depth.shape), np.float32)
            self.color = np.empty((self.size, *depth.shape, 3), np.float32)
            self._count = 0
        self._newest = (self._newest + 1) % self.size
        self.cameras[self._newest] = camera
        self.depth[self._newest] = depth
        self.color[self._newest] = color
        self._count = min(self._count + 1, self.size)

    def order(self, shape: tuple[int, int]) -> np.ndarray:
        """Ring slots of the frames with this image shape, newest first."""
        if self.depth is None or self.depth.shape[1:] != shape:
            return np.zeros(0, np.int64)
        return np.array([(self._newest - k) % self.size for k in range(self._count)], np.int64)

    def camera_stack(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        cams = [camera_arrays(self.cameras[s]) for s in slots]
        if not cams:
            return np.zeros((0, 3)), np.zeros((0, 3, 3)), np.zeros((0, 6))
        return (
            np.stack([c.position for c in cams]),
            np.stack([c.rotation for c in cams]),
            np.stack([c.frustum for c in cams]),
        )


@nb.njit(parallel=True, cache=True, nogil=True)
def _smooth(cur_cam, depth, color, alpha, slots, positions, rotations, frusta, ring_depth, ring_color, rel_depth, out):
    h, w = depth.shape
    for y in nb.prange(h):
        wsum = np.empty(w)
        acc = np.empty((w, 3))
        points = np.empty((w, 3))
        for x in range(w):
            # the weights a (1 - a)^i over their sum, with the common factor a taken out: at a = 0 (the limit)
            # they are equal, where a (1 - a)^i / sum would be 0 / 0
            wsum[x] = 1.0
            for c in range(3):
                acc[x, c] = color[y, x, c]
            points[x, 0], points[x, 1], points[x, 2] = world_point(cur_cam, x + 0.5, y + 0.5, depth[y, x])
        for i in range(slots.shape[0]):
            cam = CameraArrays(positions[i], rotations[i], frusta[i])
            d_prev, c_prev = ring_depth[slots[i]], ring_color[slots[i]]
            for x in range(w):
                qx, qy, dist = project(cam, points[x, 0], points[x, 1], points[x, 2])
                j = nearest_index(qx, qy, w, h)
                if j < 0:
                    continue
                d = d_prev[j // w, j % w]
                same = math.isinf(d) if math.isinf(depth[y, x]) else abs(d - dist) <= rel_depth * dist
                if same:
                    weight = (1.0 - alpha[y, x]) ** (i + 1)
                    r, g, b = bilinear3(c_prev, qx, qy)
                    wsum[x] += weight
                    acc[x, 0] += weight * r
                    acc[x, 1] += weight * g
                    acc[x, 2] += weight * b
        for x in range(w):
            for c in range(3):
                out[y, x, c] = acc[x, c] / wsum[x]


def exponential_smoothing(
    camera: EyeCamera,
    depth: np.ndarray,
    color: np.ndarray,
    alpha: np.ndarray,
    history: History,
    frames: int,
    rel_depth: float,
) -> np.ndarray:
    """kim2021's closed form C*_t(p) = sum_i a (1 - a)^i C(pi_{t-i}(p)) / sum_i a (1 - a)^i over the
    current frame and up to `frames` earlier ones (newest first) whose back-projected pixel sees the
    same surface: relative distance difference within rel_depth (misses match misses). alpha in [0, 1]; at
    alpha = 0 the frames weigh alike (the limit of the closed form), at alpha = 1 only the current one counts."""
    slots = history.order(depth.shape)[:frames]
    out = np.empty_like(color)
    if len(slots) == 0:
        out[:] = color
        return out
    _smooth(
        camera_arrays(camera),
        depth,
        color,
        alpha.astype(np.float32),
        slots,
        *history.camera_stack(slots),
        history.depth,
        history.color,
        rel_depth,
        out,
    )
    return out
