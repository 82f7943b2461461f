"""Where to trace: the papers' foveal sampling functions.

weier2016 section 3.1: the foveal function p(e), 1 inside r0, falling linearly to p_min at r1, p_min
beyond; a pixel is traced when xi_q < p(q). weier2018 section 3.1, equation (1): the transition region
sampled in polar coordinates from a low-discrepancy sequence, stored as the table S_in that moves
with the point of regard, and the static uniform table S_out of density p_min.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple

import numba as nb
import numpy as np

from hmdrt.errors import ConfigError
from hmdrt.foveation.base import Knob
from hmdrt.foveation.stages.pyramid import quincunx_offset
from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.rng import uniform
from hmdrt.optics.camera import EyeCamera

# weier2016 section 4.2, RQ2: the foveal region configurations (r0, r1, p_min); full traces every pixel
FRC_PRESETS: dict[str, tuple[float, float, float]] = {
    "small": (5.0, 10.0, 0.01),
    "medium": (10.0, 20.0, 0.05),
    "large": (15.0, 30.0, 0.1),
    "full": (math.inf, math.inf, 1.0),
}
SMALL_R0, SMALL_R1, SMALL_P_MIN = FRC_PRESETS["small"]
# weier2018 equation (1)'s radius: as printed, or with the polar Jacobian so that the per-pixel density
# falls linearly as weier2016's p(e) does
Density = Literal["printed", "linear"]
# the budget controller's knobs of a foveal region (weier2016, weier2018): down to the small configuration,
# the fovea's own size with a steep falloff
FOVEAL_REGION_KNOBS = (
    Knob("r0", SMALL_R0, foveal=True),
    Knob("r1", SMALL_R1, foveal=True),
    Knob("p_min", SMALL_P_MIN),
)


class Foveal(NamedTuple):
    """A foveal region configuration: r0 and r1 in degrees of eccentricity, p_min in [0, 1]."""

    r0: float
    r1: float
    p_min: float


def foveal_config(frc: str, r0: float | None, r1: float | None, p_min: float | None) -> Foveal:
    """A preset, with any of r0, r1, p_min overriding it; r0 must not exceed r1, radii are >= 0 (inf: no
    limit), p_min lies in [0, 1]."""
    if frc not in FRC_PRESETS:
        raise ConfigError(f"unknown foveal region configuration {frc!r}; presets: {', '.join(FRC_PRESETS)}")
    base = FRC_PRESETS[frc]
    cfg = Foveal(base[0] if r0 is None else r0, base[1] if r1 is None else r1, base[2] if p_min is None else p_min)
    if not (cfg.r0 >= 0.0 and cfg.r1 >= 0.0):  # also false for NaN
        raise ConfigError(f"r0 and r1 must be angles >= 0 degrees, got r0={cfg.r0}, r1={cfg.r1}")
    if not 0.0 <= cfg.p_min <= 1.0:
        raise ConfigError(f"p_min must lie in [0, 1], got {cfg.p_min}")
    if cfg.r0 > cfg.r1:
        raise ConfigError(f"r0 ({cfg.r0}) must not exceed r1 ({cfg.r1})")
    return cfg


@inline
def foveal_probability(e, r0, r1, p_min):
    """weier2016's p(q) at eccentricity e (degrees): 1 below r0, linear to p_min at r1, p_min beyond."""
    ramp = 1.0 - np.divide((1.0 - p_min) * (e - r0), r1 - r0)  # selects and np.divide: a loop of it vectorises
    return 1.0 if e < r0 else (p_min if e >= r1 else ramp)


@kernel
def _bernoulli_mask(ecc, r0, r1, p_min, seed, frame, out):
    h, w = ecc.shape
    for y in nb.prange(h):
        for x in range(w):
            p = foveal_probability(ecc[y, x], r0, r1, p_min)
            out[y, x] = p >= 1.0 or uniform(y * w + x + (seed << 32), 0x5A3, frame) < p


def bernoulli_mask(ecc: np.ndarray, cfg: Foveal, seed: int, frame: int) -> np.ndarray:
    """weier2016's ray generation: pixel q is traced when xi_q < p(q); a fresh xi per pixel and frame."""
    out = np.empty(ecc.shape, dtype=bool)
    _bernoulli_mask(ecc, cfg.r0, cfg.r1, cfg.p_min, seed, frame, out)
    return out


def expected_fraction(ecc: np.ndarray, cfg: Foveal) -> float:
    """The mean of p(q) over the pixels: the fraction bernoulli_mask traces on average."""
    e = ecc.astype(np.float64)
    if cfg.r1 > cfg.r0:
        ramp = 1.0 - (1.0 - cfg.p_min) * (e - cfg.r0) / (cfg.r1 - cfg.r0)
    else:
        ramp = np.full_like(e, cfg.p_min)
    return float(np.where(e < cfg.r0, 1.0, np.where(e >= cfg.r1, cfg.p_min, ramp)).mean())


def transition_radius(u: np.ndarray | float, r0: float, r1: float, p_min: float) -> np.ndarray:
    """weier2018 equation (1): r = r0 + (r1 - r0) (sqrt((p_min^2 - 1) u + 1) - 1) / (p_min - 1).

    Written as (1 + p_min) u / (sqrt((p_min^2 - 1) u + 1) + 1), the same value without the 0/0 at
    p_min = 1 (where it is u) or the cancellation near it.
    """
    u = np.asarray(u, dtype=np.float64)
    x = (1.0 + p_min) * u / (np.sqrt((p_min * p_min - 1.0) * u + 1.0) + 1.0)
    return r0 + (r1 - r0) * x


def transition_radius_linear(u: np.ndarray | float, r0: float, r1: float, p_min: float) -> np.ndarray:
    """The radius whose per-pixel density falls linearly from 1 at r0 to p_min at r1: the density of r is
    f(r) r (the polar Jacobian that equation (1) as printed leaves out), inverted by bisection on its cubic
    distribution function, monotone on [r0, r1] since f >= p_min >= 0."""
    u = np.asarray(u, dtype=np.float64)
    a, span = 1.0 - p_min, r1 - r0

    def cdf(x: np.ndarray) -> np.ndarray:  # of x = (r - r0) / (r1 - r0), unnormalised
        return r0 * x + (span - a * r0) * x * x / 2.0 - a * span * x**3 / 3.0

    target = u * cdf(np.float64(1.0))
    lo, hi = np.zeros_like(u), np.ones_like(u)
    for _ in range(52):  # to float64 resolution on [0, 1]
        mid = 0.5 * (lo + hi)
        below = cdf(mid) < target
        lo, hi = np.where(below, mid, lo), np.where(below, hi, mid)
    return r0 + span * 0.5 * (lo + hi)


def halton(index: np.ndarray, base: int) -> np.ndarray:
    """The radical inverse of integers in a prime base: a low-discrepancy sequence in [0, 1)."""
    index = np.asarray(index, dtype=np.int64).copy()
    out = np.zeros(index.shape, dtype=np.float64)
    f = 1.0 / base
    while np.any(index > 0):
        out += f * (index % base)
        index //= base
        f /= base
    return out


def pixels_per_degree(camera: EyeCamera) -> tuple[float, float]:
    """Pixel density along x and y at the centre of the projection (where d tan(theta) = d theta)."""
    per_rad_x = camera.width / (camera.tan_right - camera.tan_left)
    per_rad_y = camera.height / (camera.tan_up - camera.tan_down)
    return per_rad_x * math.pi / 180.0, per_rad_y * math.pi / 180.0


class SamplingTables(NamedTuple):
    """weier2018's S_in (offsets in degrees around the point of regard, at the image centre's pixels per degree)
    and S_out (static, density p_min)."""

    s_in: np.ndarray  # (2 ry + 1, 2 rx + 1) bool, centre = the point of regard
    s_out: np.ndarray  # (height, width) bool
    samples: int  # points drawn by equation (1) for the transition region
    ppd: tuple[float, float]


def transition_points(cfg: Foveal, count: int, ppd: tuple[float, float], density: Density = "printed") -> np.ndarray:
    """weier2018 equation (1)'s points as pixel offsets (count, 2) from the point of regard: r from the
    equation and phi = 2 pi v, (u, v) from the Halton (2, 3) sequence (indices from 1).

    As printed, the equation gives r the density f(x) without the polar Jacobian r, so the points are
    denser per pixel near r0 than the linear falloff, and some there share a pixel; density "linear" draws r
    with the Jacobian (transition_radius_linear).
    """
    k = np.arange(1, count + 1)
    radius = transition_radius if density == "printed" else transition_radius_linear
    r = radius(halton(k, 2), cfg.r0, min(cfg.r1, 180.0), cfg.p_min)
    phi = 2.0 * np.pi * halton(k, 3)
    return np.stack([r * np.cos(phi) * ppd[0], r * np.sin(phi) * ppd[1]], axis=1)


def sampling_tables(camera: EyeCamera, cfg: Foveal, seed: int = 0, density: Density = "printed") -> SamplingTables:
    """Precompute S_in and S_out for a camera (weier2018 section 3.1).

    S_in holds every offset inside r0 and, in [r0, r1), the texels of transition_points; their number M is
    the expected number of transition pixels under weier2016's linear falloff, their radii drawn as `density`
    says (transition_points). A point whose texel an earlier one took moves along its circle to the nearest free
    texel (_place), so that M points mark M texels at the radii the equation gave them. S_out is a seeded
    uniform pattern of density p_min.
    """
    ppd = pixels_per_degree(camera)
    r1 = min(cfg.r1, 180.0)
    rx, ry = math.ceil(r1 * ppd[0]) + 1, math.ceil(r1 * ppd[1]) + 1
    oy, ox = np.mgrid[-ry : ry + 1, -rx : rx + 1]
    r_deg = np.hypot(ox / ppd[0], oy / ppd[1])
    s_in = r_deg < cfg.r0
    band = (r_deg >= cfg.r0) & (r_deg < r1)
    samples = 0
    if band.any() and r1 > cfg.r0:
        p = 1.0 - (1.0 - cfg.p_min) * (r_deg[band] - cfg.r0) / (r1 - cfg.r0)
        samples = int(round(p.sum()))
        _place(transition_points(cfg, samples, ppd, density), np.array(ppd), s_in)
    rng = np.random.default_rng(seed)
    s_out = rng.random((camera.height, camera.width)) < cfg.p_min
    return SamplingTables(s_in, s_out, samples, ppd)


@serial
def _place(points, ppd, s_in):
    """Mark each point's texel of S_in (its offset from the centre in pixels); a point whose texel is taken
    steps along its own circle, a texel at a time in either direction, to the nearest free one. Where the
    circle is full (equation (1) as printed asks for more than one sample per texel next to r0) it is left out.
    Rounding the points alone loses about a quarter of them next to r0, where the density is near 1."""
    ry, rx = s_in.shape[0] // 2, s_in.shape[1] // 2
    for k in range(points.shape[0]):
        x, y = points[k, 0], points[k, 1]
        rpx = math.sqrt(x * x + y * y)
        if rpx == 0.0:
            s_in[ry, rx] = True
            continue
        r, phi = math.hypot(x / ppd[0], y / ppd[1]), math.atan2(y / ppd[1], x / ppd[0])
        dphi = 1.0 / rpx  # about a texel along the circle
        for s in range(int(math.pi / dphi) + 2):
            placed = False
            for sign in (1.0, -1.0):
                a = phi + sign * s * dphi
                ix = rx + int(math.floor(r * math.cos(a) * ppd[0] + 0.5))
                iy = ry + int(math.floor(r * math.sin(a) * ppd[1] + 0.5))
                if 0 <= iy < s_in.shape[0] and 0 <= ix < s_in.shape[1] and not s_in[iy, ix]:
                    s_in[iy, ix] = True
                    placed = True
                    break
            if placed:
                break


@kernel
def _table_mask(ecc, frustum, basis, r0, r1, s_in, s_out, ppd_x, ppd_y, out, counts):
    """table_mask's rows, and how many pixels of each row it selects. A transition pixel reads S_in at its offset
    from the point of regard in angle space: its eccentricity along its azimuth about the gaze (basis: the unit
    vectors u and v across the gaze), at S_in's degrees per texel."""
    h, w = ecc.shape
    tan_l, tan_r, tan_u, tan_d = frustum[0], frustum[1], frustum[2], frustum[3]
    sx, sy = (tan_r - tan_l) / w, (tan_u - tan_d) / h
    ux, uy, uz, vx, vy, vz = basis[0], basis[1], basis[2], basis[3], basis[4], basis[5]
    ry, rx = s_in.shape[0] // 2, s_in.shape[1] // 2
    for y in nb.prange(h):
        n = 0
        ty = tan_u - (y + 0.5) * sy
        for x in range(w):
            e = ecc[y, x]
            if e < r0:
                v = True
            elif e < r1:
                tx = tan_l + (x + 0.5) * sx
                a_u, a_v = tx * ux + ty * uy - uz, tx * vx + ty * vy - vz  # the view ray (tx, ty, -1) across the gaze
                norm = math.sqrt(a_u * a_u + a_v * a_v)
                cu, cv = (a_u / norm, a_v / norm) if norm > 0.0 else (1.0, 0.0)
                ix = rx + int(math.floor(e * cu * ppd_x + 0.5))
                iy = ry + int(math.floor(-e * cv * ppd_y + 0.5))  # S_in's rows run down, as the image's
                if 0 <= iy < s_in.shape[0] and 0 <= ix < s_in.shape[1]:
                    v = s_in[iy, ix]
                else:  # only where rounding leaves S_in's last texel: the density outside r1
                    v = s_out[y, x]
            else:
                v = s_out[y, x]
            out[y, x] = v
            n += v
        counts[y] = n


def gaze_basis(gaze: np.ndarray) -> np.ndarray:
    """(ux, uy, uz, vx, vy, vz): unit vectors across the unit gaze g (head frame), u toward the head's +x and
    v = u x g toward its +y, so that for a gaze ahead they are the image's right and up."""
    g = np.asarray(gaze, dtype=np.float64)
    g = g / np.linalg.norm(g)
    for axis in (np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])):
        u = axis - (axis @ g) * g
        if np.linalg.norm(u) > 1e-6:
            break
    u /= np.linalg.norm(u)
    return np.concatenate([u, np.cross(u, g)])


def _mask_into(cam: EyeCamera, gaze: np.ndarray, ecc: np.ndarray, cfg: Foveal, tables: SamplingTables, out, counts):
    frustum = np.array(cam._frustum()[:4], dtype=np.float64)
    r1 = min(cfg.r1, 180.0)
    _table_mask(ecc, frustum, gaze_basis(gaze), cfg.r0, r1, tables.s_in, tables.s_out, *tables.ppd, out, counts)


def table_mask(cam: EyeCamera, gaze: np.ndarray, ecc: np.ndarray, cfg: Foveal, tables: SamplingTables) -> np.ndarray:
    """weier2018's ray generation: S_in inside r1, S_out outside. S_in holds offsets in degrees around the point
    of regard (at the image centre's pixels per degree); each transition pixel reads it at its own offset from the
    gaze in angle space, so that every eccentricity gets equation (1)'s density wherever the gaze is, also off-axis
    where the image plane stretches angles."""
    out = np.empty(ecc.shape, dtype=bool)
    _mask_into(cam, gaze, ecc, cfg, tables, out, np.empty(ecc.shape[0], np.int64))
    return out


@inline
def footprint_level(p):
    """weier2018 section 3.1: the pyramid level of a sample's footprint, the sample spacing 1 / sqrt(p) at
    sampling density p (level 0 where every pixel is traced)."""
    return math.log2(max(1.0 / math.sqrt(max(p, 1e-6)), 1.0))


@kernel
def _list_samples(mask, starts, ecc, cfg, pixels, xy, level, offset):
    """The selected pixels row by row from starts[y]: row-major index, centre, footprint level and the
    quincunx offset on that level."""
    h, w = mask.shape
    for y in nb.prange(h):
        s = starts[y]
        for x in range(w):
            if mask[y, x]:
                pixels[s] = y * w + x
                xy[s, 0], xy[s, 1] = x + 0.5, y + 0.5
                level[s] = footprint_level(foveal_probability(ecc[y, x], cfg.r0, cfg.r1, cfg.p_min))
                offset[s] = quincunx_offset(level[s])
                s += 1


class SampleSet:
    """One eye's weier2018 samples for a point of regard, kept across frames: the mask of traced pixels, their
    row-major indices, pixel centres, footprint levels and quincunx offsets. update() recomputes them only
    when its key (what the caller says they depend on: frustum, gaze, tables) changes, into buffers that only
    grow."""

    def __init__(self) -> None:
        self.key: object = None
        self.mask = np.zeros((0, 0), bool)
        self.count = 0
        self._starts = np.zeros(1, np.int64)
        self._pixels = np.zeros(0, np.int64)
        self._xy = np.zeros((0, 2), np.float32)
        self._level = np.zeros(0, np.float64)
        self._offset = np.zeros(0, np.float64)

    def update(
        self, key: object, cam: EyeCamera, gaze: np.ndarray, ecc: np.ndarray, cfg: Foveal, tables: SamplingTables
    ) -> None:
        if key == self.key:
            return
        h, w = ecc.shape
        if self.mask.shape != (h, w):
            self.mask = np.empty((h, w), bool)
            self._starts = np.zeros(h + 1, np.int64)
        r1 = min(cfg.r1, 180.0)
        _mask_into(cam, gaze, ecc, cfg, tables, self.mask, self._starts[1:])
        np.cumsum(self._starts[1:], out=self._starts[1:])
        self.count = n = int(self._starts[-1])
        if len(self._pixels) < n:
            size = h * w  # the bound, once: the count varies as the gaze moves, and untouched pages cost nothing
            self._pixels, self._level, self._offset = np.empty(size, np.int64), np.empty(size), np.empty(size)
            self._xy = np.empty((size, 2), np.float32)
        _list_samples(self.mask, self._starts, ecc, Foveal(cfg.r0, r1, cfg.p_min), *self._buffers())
        self.key = key

    def _buffers(self) -> tuple[np.ndarray, ...]:
        return self._pixels, self._xy, self._level, self._offset

    def update_all(self, ecc: np.ndarray) -> None:
        """Every pixel, at footprint level 0 (weier2018 section 4.1's full mode), listed once per image size."""
        h, w = ecc.shape
        if self.key == ("all", h, w):
            return
        self.mask = np.ones((h, w), bool)
        self._starts = np.arange(0, (h + 1) * w, w, dtype=np.int64)
        self.count = n = h * w
        self._pixels, self._level, self._offset = np.empty(n, np.int64), np.empty(n), np.empty(n)
        self._xy = np.empty((n, 2), np.float32)
        _list_samples(self.mask, self._starts, ecc, Foveal(math.inf, math.inf, 1.0), *self._buffers())
        self.key = ("all", h, w)

    @property
    def pixels(self) -> np.ndarray:
        """(count,) int64 row-major indices of the traced pixels, ascending."""
        return self._pixels[: self.count]

    @property
    def starts(self) -> np.ndarray:
        """(height + 1,) int64 each pixel row's first sample, then the count."""
        return self._starts

    @property
    def xy(self) -> np.ndarray:
        """(count, 2) float32 their pixel centres."""
        return self._xy[: self.count]

    @property
    def level(self) -> np.ndarray:
        """(count,) float64 their footprint levels (footprint_level of p(e))."""
        return self._level[: self.count]

    @property
    def offset(self) -> np.ndarray:
        """(count,) float64 the quincunx offsets on those levels (pyramid.quincunx_offset)."""
        return self._offset[: self.count]
