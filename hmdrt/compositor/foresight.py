"""What a frame will cost before it is rendered, at each level of the budget controller (hmdrt.compositor.controller,
"Foresight"): a probe of the fovea where the gaze is about to be, and a model of the rest of the frame.

A frame's cost rests on what its fovea looks at: on `whitted` a fovea on a glass sphere traces twice the rays of one
on the floor (reflections and refractions three deep, each with its shadow rays), and the frame that lands there
after a saccade is the one that misses, before any feedback can act (docs/performance.md, "Goal 4 on the EPYC"). So
the probe traces, with the frame's own tracer, every `stride`-th pixel along x and y of the square of half-width
radius_deg around the gaze (the foveal region a method traces at its full rate; rrm's rectangle, smith2013 section
3.2.1), and counts the rays per pixel: about 200 samples at 640x720, half a millisecond.

The model (CostModel) splits each frame it learns of into the fovea's rays (the probe's rays per pixel times the
fovea's pixels) at what a foveal ray costs, and the rest (periphery, reuse, passes) in nanoseconds, kept per level,
and predicts a frame at a level as the rest at that level plus the fovea's rays where the gaze now is. A foveal ray's
cost is the slope of render time over the fovea's rays within a level (on glass, reflected and refracted rays: at
rrm's level 1 on the EPYC 117 ns against the rest's 59), the mean ray's until the rays have spread. A level other
than the last frame's also costs what a change of the knobs has cost the method: how much more its prediction fell
short on frames after a change than on the others (flipping the level every frame at 640x720 costs rrm nothing
measurable, its fovea placed anew every frame, and weier16, kim21 and weier18 4-16 ms, their samples, tables or
reuse rebuilt).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from hmdrt.foveation.stages.sampling import pixels_per_degree
from hmdrt.optics.camera import EyeCamera
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

GRID = 20  # levels the model knows: 0, 1 / GRID, ..., 1
SMOOTHING = 0.3  # weight of the newest frame in the model's running means
SLOW = 0.02  # and in the covariance that tells a foveal ray's cost apart (a landing or two a second)
STALE = 300  # frames after which a level's rest gives way to its fresher neighbours' (10 s at 30 Hz)
SPREAD = 0.1  # the foveal rays' spread about their level's mean, relative to their size, that a slope needs


class Foresight(NamedTuple):
    """The probe's reading: rays per pixel of the foveal squares, the pixels they cover (both eyes) and the foveal
    radius they were read at."""

    rays_per_pixel: float
    pixels: int
    radius_deg: float

    def rays(self, radius_deg: float) -> float:
        """The fovea's rays at another radius, its pixels scaling with the square's area (clipping aside)."""
        if self.radius_deg <= 0.0:
            return 0.0
        return self.rays_per_pixel * self.pixels * (radius_deg / self.radius_deg) ** 2


class FovealProbe:
    """Traces a sparse grid of the foveal square around the gaze with `tracer`."""

    def __init__(self, tracer: Whitted, stride: int = 8):
        if stride < 1:
            raise ValueError(f"stride must be at least 1, got {stride}")
        self.tracer = tracer
        self.stride = stride
        self._xy = np.empty((0, 2), np.float32)
        self._keys = np.empty(0, np.int64)
        self._out = np.empty((0, 3), np.float32)

    def read(self, cameras: dict[str, EyeCamera], gazes: dict[str, np.ndarray], radius_deg: float) -> Foresight:
        """The rays per pixel of the first eye's square of half-width radius_deg around its gaze (head frame), clipped
        to the image, and the pixels of every eye's square, taken as that eye's: the eyes verge on the same surface,
        and a second call would cost a second dispatch to the tracer's threads (0.2 ms). No pixels (and 0 rays)
        where the square lies off the image."""
        eye, camera = next(iter(cameras.items()))
        n, covered = self._grid(camera, gazes[eye], radius_deg)
        if not n:
            return Foresight(0.0, 0, radius_deg)
        stats = FrameStats()
        self.tracer.trace_samples(camera, self._xy[:n], self._keys[:n], stats, out=self._out[:n])
        return Foresight(sum(stats.rays.values()) / n, covered * len(cameras), radius_deg)

    def _grid(self, camera: EyeCamera, gaze: np.ndarray, radius_deg: float) -> tuple[int, int]:
        """Pixel centres every `stride` pixels of the square into self._xy: their count and the pixels covered."""
        gx, gy = camera.gaze_pixel(gaze)
        ppd_x, ppd_y = pixels_per_degree(camera)
        x0, x1 = _span(gx, radius_deg * ppd_x, camera.width)
        y0, y1 = _span(gy, radius_deg * ppd_y, camera.height)
        xs = np.arange(x0, x1, self.stride, dtype=np.float32) + np.float32(0.5)
        ys = np.arange(y0, y1, self.stride, dtype=np.float32) + np.float32(0.5)
        n = len(xs) * len(ys)
        if n > len(self._keys):
            self._xy, self._out = np.empty((n, 2), np.float32), np.empty((n, 3), np.float32)
            self._keys = np.arange(n, dtype=np.int64)
        grid = self._xy[:n].reshape(len(ys), len(xs), 2)
        grid[:, :, 0], grid[:, :, 1] = xs[None, :], ys[:, None]
        return n, (x1 - x0) * (y1 - y0)


def _span(centre: float, half: float, size: int) -> tuple[int, int]:
    """The pixels [lo, hi) within `half` of `centre`, clipped to [0, size)."""
    lo = min(max(math.floor(centre - half), 0), size)
    return lo, max(lo, min(math.ceil(centre + half), size))


class CostModel:
    """Render time predicted per level (module docstring): the time of the rest of a frame at each level of the grid,
    and the nanoseconds a foveal ray costs, as running means over the frames learnt of."""

    def __init__(self) -> None:
        self._rest = [math.nan] * (GRID + 1)  # ns of what is not the fovea's rays, per level
        self._learnt = [-STALE] * (GRID + 1)  # when each level's rest was last learnt, in frames learnt
        self._frames = 0
        self._fresh: tuple[int, list[bool]] = (-1, [])
        self._fovea = [math.nan] * (GRID + 1)  # mean foveal rays per level, for the covariance below
        self._time = [math.nan] * (GRID + 1)  # mean render ns per level
        self._cov = self._var = math.nan  # of render time and foveal rays about their level's means
        self._square = math.nan  # the foveal rays' mean square: how much spread tells a slope apart
        self._ns_per_ray = math.nan  # over all rays: a foveal ray's cost until the covariance tells it apart
        self._short = {False: math.nan, True: math.nan}  # what predictions fell short by, without and after a change

    @property
    def change_ns(self) -> float:
        """What a change of level costs beyond the new level's own time (0 until frames of both kinds are learnt)."""
        extra = self._short[True] - self._short[False]
        return 0.0 if math.isnan(extra) else max(extra, 0.0)

    @property
    def ns_per_foveal_ray(self) -> float:
        """The slope of render time over the fovea's rays within a level, bounded to 0.5-4x the mean ray's cost; the
        mean ray's cost until the fovea's rays have spread by a tenth of their size."""
        mean = self._ns_per_ray
        if math.isnan(self._var) or self._var <= SPREAD**2 * self._square:
            return mean
        return min(max(self._cov / self._var, 0.5 * mean), 4.0 * mean)

    def learn(self, level: float, radius_deg: float, render_ns: int, rays: int, fore: Foresight, changed: bool) -> None:
        """A frame rendered at `level` with a foveal radius of radius_deg in render_ns with `rays`, its fovea read as
        `fore` before it; `changed`: its level was not the frame's before."""
        if rays <= 0 or render_ns <= 0:
            return
        ahead = self.predict(level, fore, radius_deg)
        if not math.isnan(ahead):
            self._short[changed] = _running(self._short[changed], render_ns - ahead)
        i, fovea = round(level * GRID), fore.rays(radius_deg)
        self._ns_per_ray = _running(self._ns_per_ray, render_ns / rays)
        self._square = _running(self._square, fovea * fovea, SLOW)
        if not math.isnan(self._time[i]):
            df, dt = fovea - self._fovea[i], render_ns - self._time[i]
            self._cov = _running(self._cov, df * dt, SLOW)
            self._var = _running(self._var, df * df, SLOW)
        self._fovea[i] = _running(self._fovea[i], fovea)
        self._time[i] = _running(self._time[i], render_ns)
        self._rest[i] = _running(self._rest[i], render_ns - self.ns_per_foveal_ray * fovea)
        self._frames += 1
        self._learnt[i] = self._frames

    def predict(self, level: float, fore: Foresight, radius_deg: float) -> float:
        """Nanoseconds a frame at `level` with a foveal radius of radius_deg would take where the probe read `fore`;
        NaN before any frame is learnt. The rest at a level not seen in the last STALE frames is taken from the
        levels around it that were (interpolated, or the nearest): a level left long ago (the warm-up's slow frames,
        a busier machine) must not hold the controller below it."""
        return self._rest_at(round(level * GRID)) + self.ns_per_foveal_ray * fore.rays(radius_deg)

    def _rest_at(self, i: int) -> float:
        if self._fresh[0] != self._frames:  # which levels are fresh changes only when a frame is learnt
            rests = zip(self._rest, self._learnt, strict=True)
            self._fresh = (self._frames, [not math.isnan(r) and self._frames - t < STALE for r, t in rests])
        fresh = self._fresh[1]
        if fresh[i]:
            return self._rest[i]
        below = next((j for j in range(i - 1, -1, -1) if fresh[j]), None)
        above = next((j for j in range(i + 1, GRID + 1) if fresh[j]), None)
        if below is None or above is None:
            nearest = above if below is None else below
            return math.nan if nearest is None else self._rest[nearest]
        w = (i - below) / (above - below)
        return (1 - w) * self._rest[below] + w * self._rest[above]


def _running(mean: float, value: float, weight: float = SMOOTHING) -> float:
    return value if math.isnan(mean) else mean + weight * (value - mean)
