"""Combining frames over time.

weier2016 section 3.4: the running estimate with alpha' = 1 / (rho + 1), rho the accumulated sample
count, and the age-dependent lower bound k(dt) between k_min and k_max over t_max frames.
kim2021 section 4.7: exponential smoothing over up to four back-projected earlier frames, in closed
form, with an eccentricity-dependent blending factor alpha(e). Both keep per-eye history.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.memory import touched
from hmdrt.kernels.schedule import claim, dynamic
from hmdrt.kernels.simd import rgb_accumulate, rgb_bilinear_add
from hmdrt.optics.camera import EyeCamera
from hmdrt.optics.projection import FAR, bilinear_footprint, camera_arrays, pixel_tangents


@inline
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


AGES = 256  # the whole ages, in frames, that an age_table holds


@serial
def age_table(k_min, k_max, t_max, out):
    """out[i] = k_of_age(i, ...) for each whole age i below len(out): what k_at reads instead of an exp per sample."""
    for i in range(out.shape[0]):
        out[i] = k_of_age(float(i), k_min, k_max, t_max)


@inline
def k_at(table, dt, k_min, k_max, t_max):
    """k_of_age(dt, ...): table[dt] (age_table) where dt is a whole age the table holds, as ages counted in whole
    frames are, else computed; the same value either way."""
    i = int(dt)
    if 0 <= i < table.shape[0] and i == dt:
        return table[i]
    return k_of_age(dt, k_min, k_max, t_max)


@inline
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
    """The last `size` frames of one eye (camera, hit distance (inf on a miss), colour) in preallocated rings with
    one slot more, which the frame being rendered is written into in place (begin, then commit), so that no frame
    is copied. A change of image size starts the history afresh, and so does restart(), which keeps the newest
    frame readable (newest) but takes every frame out of order()."""

    def __init__(self, size: int):
        self.size = size
        self.cameras: list[EyeCamera | None] = [None] * (size + 1)
        self.depth: np.ndarray | None = None  # (size + 1, h, w) float32
        self.color: np.ndarray | None = None  # (size + 1, h, w, 3) float32, a spare float after it (begin)
        self.scratch: np.ndarray | None = None  # (threads, ROW, w) float64: what smoothing keeps of a row
        self.taps: np.ndarray | None = None  # (threads, TAPS, w) uint64: and its footprints
        self._newest = -1
        self._count = 0

    def begin(self, shape: tuple[int, int]) -> int:
        """The ring slot the next frame goes in; its depth and colour are the caller's to fill before commit."""
        if self.depth is None or self.depth.shape[1:] != shape:
            self.depth = touched((self.size + 1, *shape))  # each slot is first written a frame later
            # with a spare float after the ring: simd.rgb_accumulate's 16-byte load of the last texel reads it
            texels = (self.size + 1) * shape[0] * shape[1]
            self.color = touched(3 * texels + 1)[:-1].reshape((self.size + 1, *shape, 3))
            self.scratch = np.empty((nb.config.NUMBA_NUM_THREADS, ROW, shape[1]))
            self.taps = np.empty((nb.config.NUMBA_NUM_THREADS, TAPS, shape[1]), np.uint64)
            self._newest, self._count = -1, 0
        return (self._newest + 1) % (self.size + 1)

    def commit(self, camera: EyeCamera) -> None:
        """The slot of begin holds the newest frame now, seen by `camera`."""
        self._newest = (self._newest + 1) % (self.size + 1)
        self.cameras[self._newest] = camera
        self._count = min(self._count + 1, self.size)

    def push(self, camera: EyeCamera, depth: np.ndarray, color: np.ndarray) -> None:
        slot = self.begin(depth.shape)
        self.depth[slot] = depth
        self.color[slot] = color
        self.commit(camera)

    def restart(self) -> None:
        self._count = 0

    def newest(self, shape: tuple[int, int]) -> int:
        """The slot of the newest frame of this image shape, even after restart; -1 if there is none."""
        return self._newest if self.depth is not None and self.depth.shape[1:] == shape else -1

    def order(self, shape: tuple[int, int]) -> np.ndarray:
        """Ring slots of the frames with this image shape, newest first."""
        if self.newest(shape) < 0:
            return np.zeros(0, np.int64)
        return np.array([(self._newest - k) % (self.size + 1) for k in range(self._count)], np.int64)


SUMS = 7  # smoothing's float values per pixel of a row: point (3), footprint weights (2), distance, fade; then
ROW = SUMS + 4  # its colour sums and their weights' sum, interleaved (simd.rgb_bilinear_add adds a tap to all four)
TAPS = 4  # and its integer ones: the depth texel, the colour footprint's first element and steps (_footprints)


class Earlier(NamedTuple):
    """The earlier frames a smoothing pass blends, newest first, and the history rings they are in."""

    slots: np.ndarray  # (k,) int64 ring slots
    views: np.ndarray  # (k, VIEW) float64 each frame's view of the current camera's points (relative_view)
    same: np.ndarray  # (k,) bool: the frame's camera is the current one, so each pixel sees itself there
    depth: np.ndarray  # (size + 1, h, w) float32 ring
    color: np.ndarray  # (size + 1, h, w, 3) float32 ring
    scratch: np.ndarray  # (threads, ROW, w) float64: one row's values per numba thread (nb.get_thread_id())
    taps: np.ndarray  # (threads, TAPS, w) uint64: one row's footprints per numba thread, -1 where off the image


VIEW = 16  # relative_view: M (9), t (3), tan_left, width / (tan_right - tan_left), tan_up, height / (tan_up - tan_down)


def relative_view(earlier: EyeCamera, current: EyeCamera) -> np.ndarray:
    """How `earlier` sees points given in `current`'s eye frame: p_earlier = M p_current + t, with the constants
    that take its eye frame to continuous pixel coordinates, so that a back-projection is one matrix product."""
    out = np.empty(VIEW)
    out[:9] = (earlier.rotation.T @ current.rotation).reshape(-1)
    out[9:12] = earlier.rotation.T @ (current.position - earlier.position)
    out[12] = earlier.tan_left
    out[13] = earlier.width / (earlier.tan_right - earlier.tan_left)
    out[14] = earlier.tan_up
    out[15] = earlier.height / (earlier.tan_up - earlier.tan_down)
    return out


@inline
def ray_point(tx, ty, depth):
    """The point at hit distance `depth` (FAR for a miss) along the view ray with tangents (tx, ty)
    (projection.pixel_tangents), in its camera's eye frame."""
    s = np.divide(min(depth, FAR), math.sqrt(tx * tx + ty * ty + 1.0))
    return s * tx, s * ty, -s


@inline
def eye_point(frustum, x, y, depth):
    """The point at hit distance `depth` (FAR for a miss) along the view ray through continuous pixel (x, y), in
    the eye frame of the camera with this frustum (CameraArrays.frustum)."""
    tx, ty = pixel_tangents(frustum, x, y)
    return ray_point(tx, ty, depth)


@inline
def view_project(v, px, py, pz):
    """Continuous pixel coordinates and distance of eye-frame point p in the camera of relative_view v; x is -1
    behind that camera."""
    lx = v[0] * px + v[1] * py + v[2] * pz + v[9]
    ly = v[3] * px + v[4] * py + v[5] * pz + v[10]
    lz = v[6] * px + v[7] * py + v[8] * pz + v[11]
    iz = np.divide(-1.0, lz)
    qx = (lx * iz - v[12]) * v[13] if lz < 0.0 else -1.0
    return qx, (v[14] - ly * iz) * v[15], math.sqrt(lx * lx + ly * ly + lz * lz)


def same_camera(a: EyeCamera | None, b: EyeCamera) -> bool:
    """Whether two cameras see every pixel along the same ray."""
    if a is b:
        return True
    return (
        a is not None
        and a._frustum() == b._frustum()
        and np.array_equal(a.position, b.position)
        and np.array_equal(a.rotation, b.rotation)
    )


def earlier_frames(history: History, camera: EyeCamera, shape: tuple[int, int], frames: int) -> Earlier:
    slots = history.order(shape)[:frames]
    views = np.empty((len(slots), VIEW))
    for k, s in enumerate(slots):
        views[k] = relative_view(history.cameras[s], camera)
    same = np.array([same_camera(history.cameras[s], camera) for s in slots], bool)
    return Earlier(slots, views, same, history.depth, history.color, history.scratch, history.taps)


@serial
def _footprints(view, px, py, pz, h, qx, qy, dist, near, corner, step_x, step_y):
    """A row's points (px, py, pz) back-projected by `view` (view_project) into an earlier frame of height h and
    the row's width: their distances there, and as flat indices into it the texel whose depth the test reads (-1
    off the image) and the first element and the x and y steps of the colour's bilinear footprint (the clamped
    texels of projection.bilinear3), whose weights replace the coordinates in qx and qy. Selects and stores only,
    in two loops over the row, so that both vectorise."""
    w = len(px)
    for x in range(w):
        qx[x], qy[x], dist[x] = view_project(view, px[x], py[x], pz[x])
    for x in range(w):
        cx, cy = qx[x], qy[x]
        inside = (cx >= 0.0) & (cy >= 0.0) & (cx < w) & (cy < h)
        near[x] = np.uint64(min(max(int(cy), 0), h - 1) * w + min(max(int(cx), 0), w - 1) if inside else -1)
        qx[x], qy[x], corner[x], step_x[x], step_y[x] = bilinear_footprint(cx, cy, w, h)


@serial
def _smooth_row(y, frustum, depth, color, alpha, earlier, rel_depth, out, row, taps):
    """Row y of the closed form, in passes over the row so that the back-projections vectorise: the pixels' points
    at their hit distances (FAR for a miss) in the current eye frame, then per earlier frame their footprints
    there (_footprints), then the depth test and the blend. Frames seen by the current camera read the pixel
    itself."""
    slots, views, same, ring_depth, ring_color, _, _ = earlier
    h, w = depth.shape
    px, py, pz, ax, ay, dists, fade = row[0], row[1], row[2], row[3], row[4], row[5], row[6]
    sums = row[SUMS:].reshape(-1)  # per pixel its colour sums and their weights' sum, four in a row
    for x in range(w):
        px[x], py[x], pz[x] = eye_point(frustum, x + 0.5, y + 0.5, depth[y, x])
        s = 4 * x
        sums[s], sums[s + 1], sums[s + 2] = color[y, x, 0], color[y, x, 1], color[y, x, 2]
        # the weights a (1 - a)^i over their sum, with the common factor a taken out: at a = 0 (the limit)
        # they are equal, where a (1 - a)^i / sum would be 0 / 0
        sums[s + 3] = fade[x] = 1.0
    near_row, corner_row, step_x_row, step_y_row = taps[0], taps[1], taps[2], taps[3]
    off = np.uint64(-1)
    for k in range(slots.shape[0]):
        image, image_depth = ring_color[slots[k]].reshape(-1), ring_depth[slots[k]].reshape(-1)
        for x in range(w):
            fade[x] *= 1.0 - alpha[y, x]  # (1 - a)^(k + 1)
        if same[k]:
            for x in range(w):
                near_row[x] = np.uint64(y * w + x)
                dists[x] = min(np.float64(depth[y, x]), FAR)
        else:
            _footprints(views[k], px, py, pz, h, ax, ay, dists, near_row, corner_row, step_x_row, step_y_row)
        for x in range(w):
            near = near_row[x]
            if near == off:
                continue
            d, dist = depth[y, x], dists[x]
            d_prev = image_depth[near]
            if not (math.isinf(d_prev) if math.isinf(d) else abs(d_prev - dist) <= rel_depth * dist):
                continue
            weight, s = fade[x], 4 * x
            if same[k]:
                i = np.uint64(3) * near
                sums[s] += weight * image[i]
                sums[s + 1] += weight * image[i + np.uint64(1)]
                sums[s + 2] += weight * image[i + np.uint64(2)]
                sums[s + 3] += weight
            else:
                rgb_bilinear_add(sums, s, weight, image, corner_row[x], step_x_row[x], step_y_row[x], ax[x], ay[x])
    for x in range(w):
        s = 4 * x
        wsum = sums[s + 3]
        r, g, b = np.divide(sums[s], wsum), np.divide(sums[s + 1], wsum), np.divide(sums[s + 2], wsum)
        out[y, x, 0], out[y, x, 1], out[y, x, 2] = r, g, b


@serial
def _smooth_still_row(y, depth, color, alpha, earlier, rel_depth, out):
    """Row y of the closed form when every earlier frame was seen by the current camera: each pixel reads itself.
    The weights (1 - a)^(k + 1) as a running product, as _smooth_row takes them (a power per frame costs more
    than the rest of the pixel's work); an earlier frame's colour added three channels at once (rgb_accumulate)."""
    slots, _, _, ring_depth, ring_color, _, _ = earlier
    ring = ring_color.reshape(-1)
    height, width = np.uint64(depth.shape[0]), np.uint64(depth.shape[1])
    y = np.uint64(y)  # unsigned indices: no negative-index wraparound on the loads
    for x in range(depth.shape[1]):
        x = np.uint64(x)
        d = depth[y, x]
        dist = min(np.float64(d), FAR)
        r, g, b = np.float64(color[y, x, 0]), np.float64(color[y, x, 1]), np.float64(color[y, x, 2])
        wsum = fade = 1.0  # as in _smooth_row
        keep = 1.0 - alpha[y, x]
        for k in range(slots.shape[0]):
            slot = np.uint64(slots[k])
            fade *= keep  # (1 - a)^(k + 1)
            d_prev = ring_depth[slot, y, x]
            if math.isinf(d_prev) if math.isinf(d) else abs(d_prev - dist) <= rel_depth * dist:
                wsum += fade
                r, g, b = rgb_accumulate(r, g, b, fade, ring, np.uint64(3) * ((slot * height + y) * width + x))
        out[y, x, 0], out[y, x, 1], out[y, x, 2] = r / wsum, g / wsum, b / wsum


@kernel
def _smooth(frustum, depth, color, alpha, earlier, rel_depth, out, counter, threads):
    """The closed form over the image: pixel by pixel when no earlier camera moved, else row by row in the scratch
    row of the thread that claims it (hmdrt.kernels.schedule: the sky's rows cost less)."""
    h = depth.shape[0]
    if earlier.same.all():
        for y in nb.prange(h):
            _smooth_still_row(np.uint64(y), depth, color, alpha, earlier, rel_depth, out)
    else:
        for _ in nb.prange(threads):
            t = nb.get_thread_id()
            row, taps = earlier.scratch[t], earlier.taps[t]
            y = claim(counter)
            while y < h:
                _smooth_row(y, frustum, depth, color, alpha, earlier, rel_depth, out, row, taps)
                y = claim(counter)


def exponential_smoothing(
    camera: EyeCamera,
    depth: np.ndarray,
    color: np.ndarray,
    alpha: np.ndarray,
    history: History,
    frames: int,
    rel_depth: float,
    out: np.ndarray | None = None,
) -> np.ndarray:
    """kim2021's closed form C*_t(p) = sum_i a (1 - a)^i C(pi_{t-i}(p)) / sum_i a (1 - a)^i over the
    current frame and up to `frames` earlier ones (newest first) whose back-projected pixel sees the
    same surface: relative distance difference within rel_depth (misses match misses). alpha (h, w) float32 in
    [0, 1]; at alpha = 0 the frames weigh alike (the limit of the closed form), at alpha = 1 only the current one
    counts. An earlier frame seen by the same camera is read pixel for pixel (where back-projection would land).
    Written into `out` (h, w, 3) float32 when given, which must not be `color`."""
    out = np.empty_like(color) if out is None else out
    earlier = earlier_frames(history, camera, depth.shape, frames)
    if len(earlier.slots) == 0:
        out[:] = color
        return out
    dynamic(_smooth, camera_arrays(camera).frustum, depth, color, alpha, earlier, rel_depth, out)
    return out
