"""Gaze-contingent depth of field (weier2018 section 3.2).

Circles of confusion from the tracking-aware thin-lens model, equation (3): the eye's image distance
d_i = 22.4 mm is fixed, the focus distance d_o is widened to d_n = d_o - t and d_f = d_o + t by the
mean depth-estimation inaccuracy t = 0.2 m, and the CoC is zero in [d_n, d_f], signed outside it
(positive near, negative far). Pupil diameter k and retinal resolution E set the strength. The
layered blur keeps near, focused and far fields apart: the far field takes a variable Gaussian that
ignores nearer pixels in central vision and the reconstruction pyramid in the periphery, blended
across the transition; the near field spreads over its neighbours with a coverage for alpha blending.

The paper names the presets but gives no numbers for them; the (k, E) below give CoC radii of about
2, 5 and 10 pixels for a point at 6 m while fixating 0.75 m at rift_s resolution (E is scaled to the
display's pixel density, so the blur spans the same visual angle on every profile). Equation (3) is
used as printed, with lengths in millimetres.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.stages.filters import Contrast, enhance_row
from hmdrt.foveation.stages.pyramid import CHANNELS, DEPTH, PixelAxes, Pyramid, RowSamples, pixel_axes, sample_row
from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.schedule import claim, dynamic

IMAGE_DISTANCE_MM = 22.4  # d_i, the eye's lens-to-retina distance (Gross 2005)
DEPTH_INACCURACY_M = 0.2  # t, the mean gaze-depth estimation error over 6 m (Weier et al. 2018)
REFERENCE_PPD = 11.44  # rift_s pixels per degree at the centre (mean of x and y), where the presets hold
MAX_BLUR_PX = 24  # radius cap of the central Gaussian and of the near-field spread
RAMP_PX = 2.0  # the |CoC| over which the sharp image fades into the far field


class DofPreset(NamedTuple):
    pupil_mm: float  # k
    retina: float  # E, pixels per mm^2 at REFERENCE_PPD


DOF_PRESETS: dict[str, DofPreset | None] = {
    "none": None,
    "weak": DofPreset(3.0, 0.07),
    "medium": DofPreset(4.0, 0.13),
    "strong": DofPreset(6.0, 0.17),
}


def focal_lengths(d_o_m: float, t_m: float = DEPTH_INACCURACY_M) -> tuple[float, float, float, float]:
    """(d_n, d_f, f_n, f_f) in mm: the widened focus range and the focal lengths that image each onto
    the retina (1/f = 1/d + 1/d_i). d_n is kept at 2 d_i or more (where d_o <= t would make it zero or
    negative), above the focal length so the lens equation holds, and d_f at d_n or more. d_o = inf gives
    d_n = d_f = inf and f_n = f_f = d_i: focused at infinity."""
    d_o = d_o_m * 1000.0
    d_n = max(d_o - t_m * 1000.0, 2.0 * IMAGE_DISTANCE_MM)
    d_f = max(d_o + t_m * 1000.0, d_n)
    f = lambda d: 1.0 / (1.0 / d + 1.0 / IMAGE_DISTANCE_MM)  # noqa: E731
    return d_n, d_f, f(d_n), f(d_f)


@serial
def _image_distance(f, g):
    """V(F, G) = F G / (G - F): where a lens of focal length F images an object at G (G > F); F at G = inf. A select
    rather than a branch and np.divide rather than `/` (no zero-division check, which G > F rules out anyway):
    a loop over pixels that calls it vectorises."""
    return f if math.isinf(g) else np.divide(f * g, g - f)


@inline
def _coc(g_mm, d_n, d_f, f_n, f_f, v_n, v_f, k, e):
    """circle_of_confusion with the images of the range's ends, v_n = V(f_n, d_n) and v_f = V(f_f, d_f), given:
    they are constant over a frame. Selects only, so that the CoC map's loop vectorises."""
    near = g_mm < d_n
    f, vd = (f_n, v_n) if near else (f_f, v_f)
    vg = _image_distance(f, max(g_mm, f * (1.0 + 1e-9)))  # an object at infinity is imaged at the focal plane
    c = (vg - vd) * (k * vg) * e
    return c if near or g_mm > d_f else 0.0


@inline
def circle_of_confusion(g_mm, d_n, d_f, f_n, f_f, k, e):
    """Equation (3): signed CoC of an object at distance g (mm); 0 inside [d_n, d_f], > 0 near, < 0 far.

    An object at or inside the focal length (g <= f: nothing closer than about 2 cm to the eye) has no real
    image; it takes the CoC of g = f (1 + 1e-9), finite and larger than any other. The blur filters cap every
    CoC at MAX_BLUR_PX (weier18 counts those pixels in its coc_capped_pixels metric)."""
    return _coc(g_mm, d_n, d_f, f_n, f_f, _image_distance(f_n, d_n), _image_distance(f_f, d_f), k, e)


class Lens(NamedTuple):
    """Equation (3)'s constants for one focus: the widened range [d_n, d_f] (mm), the focal lengths that image
    its ends onto the retina (mm), pupil diameter k (mm) and retinal resolution E at the display's density."""

    d_n: float
    d_f: float
    f_n: float
    f_f: float
    k: float
    e: float


def lens(focus_m: float, preset: DofPreset, ppd: float, t_m: float = DEPTH_INACCURACY_M) -> Lens:
    return Lens(*focal_lengths(focus_m, t_m), preset.pupil_mm, preset.retina * ppd / REFERENCE_PPD)


ROW_MAX, ROW_ABS_MAX, ROW_CAPPED = 0, 1, 2  # the per-row figures of a CoC map (Layers.rows)
_CAP_BITS = int(np.array(MAX_BLUR_PX, np.float32).view(np.int32))  # |CoC| beyond it, as float32 bits
_NEG_INF_BITS = int(np.array(-np.inf, np.float32).view(np.int32))


@serial
def _order_key(bits):
    """A float32's bits (as a sign-extended integer) to a key that orders as the floats do, or the key back to the
    bits: negative floats' bits order backwards, so their 31 low bits are flipped."""
    return bits ^ np.int64(0x7FFFFFFF) if bits < 0 else bits


@inline
def _row_stats(coc, y, rows):
    """Row y's largest CoC, largest |CoC| and count of |CoC| beyond MAX_BLUR_PX, from the CoCs' float32 bits: their
    maxima as integer maxima (_order_key; the magnitude's bits with the sign bit cleared), which vectorise, where
    float maxima do not (NaN's rules). The maxima are written into `rows` (float32) as bits."""
    bits, figures = coc[y].view(np.int32), rows[y].view(np.int32)
    top, size, capped = _order_key(np.int64(_NEG_INF_BITS)), np.int64(0), 0
    for x in range(bits.shape[0]):
        b = np.int64(bits[x])
        magnitude = b & np.int64(0x7FFFFFFF)
        top, size = max(top, _order_key(b)), max(size, magnitude)
        capped += magnitude > _CAP_BITS
    figures[ROW_MAX], figures[ROW_ABS_MAX] = _order_key(top), size
    rows[y, ROW_CAPPED] = capped


@kernel
def _coc_rows(level, miss, lens, coc, rows, counter, threads):
    """The CoC of every pixel (hit distances in metres in channel DEPTH of a pyramid level; `miss` and beyond:
    misses, at infinity) and each row's figures, rows claimed (hmdrt.kernels.schedule: a row of misses or of
    focused pixels costs less)."""
    d_n, d_f, f_n, f_f, k, e = lens
    v_n, v_f = _image_distance(f_n, d_n), _image_distance(f_f, d_f)
    h, w = coc.shape
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < h:
            for x in range(w):
                d = level[y, x, DEPTH]
                g = math.inf if d >= miss else d * 1000.0
                coc[y, x] = _coc(g, d_n, d_f, f_n, f_f, v_n, v_f, k, e)
            _row_stats(coc, y, rows)
            y = claim(counter)


@kernel
def _coc_stats(coc, rows):
    for y in nb.prange(coc.shape[0]):
        _row_stats(coc, y, rows)


class Layers(NamedTuple):
    """The layered blur's per-pixel buffers, kept across frames."""

    coc: np.ndarray  # (h, w) float32 signed CoC in pixels
    far: np.ndarray  # (h, w, 3) float32 the central far-field Gaussian after its horizontal pass
    near: np.ndarray  # (h, w, 4) float32 the near field after its horizontal pass: mean colour, reach
    rows: np.ndarray  # (h, 3) float32 each row's ROW_MAX, ROW_ABS_MAX, ROW_CAPPED

    @classmethod
    def empty(cls, width: int, height: int) -> Layers:
        return cls(
            np.zeros((height, width), np.float32),
            np.zeros((height, width, 3), np.float32),
            np.zeros((height, width, 4), np.float32),
            np.zeros((height, 3), np.float32),
        )

    def compute_coc(self, level: np.ndarray, lens: Lens, miss: float = math.inf) -> None:
        """The CoC map of a pyramid level's hit distances (channel DEPTH, m; `miss` and beyond, or inf: misses) and
        its row figures. The level is read in place: a strided view of its depth channel, or a channel index that
        is not a constant, keeps the loop from vectorising (5-10x slower at rift_s)."""
        dynamic(_coc_rows, level, miss, lens, self.coc, self.rows)

    def near_radius(self) -> int:
        """How far the near field spreads: the largest CoC, rounded up, at most MAX_BLUR_PX."""
        return min(MAX_BLUR_PX, math.ceil(max(float(self.rows[:, ROW_MAX].max()), 0.0)))

    def coc_figures(self) -> tuple[float, int]:
        """The largest |CoC| (pixels) and how many pixels the blur caps at MAX_BLUR_PX."""
        return float(self.rows[:, ROW_ABS_MAX].max()), int(self.rows[:, ROW_CAPPED].sum())


def coc_map(
    depth_m: np.ndarray, focus_m: float, preset: DofPreset, ppd: float, t_m: float = DEPTH_INACCURACY_M
) -> np.ndarray:
    """Per-pixel signed CoC in pixels for hit distances depth_m (m, inf for misses), focus widened by t_m."""
    level = np.zeros((*np.shape(depth_m), CHANNELS), np.float64)
    level[..., DEPTH] = depth_m
    layers = Layers(np.empty(level.shape[:2], np.float32), None, None, np.empty((level.shape[0], 3), np.float32))
    layers.compute_coc(level, lens(focus_m, preset, ppd, t_m))
    return layers.coc


class Blur(NamedTuple):
    """The layered blur's settings: the transition region [r0, r1) between the central Gaussian and the
    pyramid, the CoC over which the sharp image fades into the far field, the near field's search radius."""

    r0: float
    r1: float
    ramp: float = RAMP_PX
    radius: int = 0


@serial
def _gauss_radius(sigma):
    """The far Gaussian's reach, capped before the integer conversion, which would overflow for CoCs beyond
    about 1e18 pixels."""
    return MAX_BLUR_PX if sigma >= 0.5 * MAX_BLUR_PX else int(math.ceil(2.0 * sigma))


@serial
def _far_gauss(central, outside, ecc, coc, y, x, step_y, step_x, r1, c0):
    """The central far-field Gaussian of pixel (y, x) along one axis (step_y, step_x) over the far-field pixels
    only, so that the focused and near fields do not bleed into the blurred background; a tap reads `central`
    inside central vision (e < r1) and `outside` beyond it."""
    h, w = coc.shape
    sigma = max(-0.5 * c0, 0.5)
    reach = _gauss_radius(sigma)
    wsum = r = g = b = 0.0
    for d in range(-reach, reach + 1):
        yy, xx = y + d * step_y, x + d * step_x
        if yy < 0 or yy >= h or xx < 0 or xx >= w or coc[yy, xx] >= 0.0:
            continue
        wt = math.exp(-0.5 * d * d / (sigma * sigma))
        wsum += wt
        src = central if ecc[yy, xx] < r1 else outside
        r, g, b = r + wt * src[yy, xx, 0], g + wt * src[yy, xx, 1], b + wt * src[yy, xx, 2]
    return r / wsum, g / wsum, b / wsum


@serial
def _horizontal_row(color, ecc, coc, far, near, y, r1, radius, has_near):
    """Row y of the first pass: the far-field Gaussian of central pixels (_far_gauss); and the near field, where
    each pixel averages the near-field pixels (CoC > 0) whose blur disc reaches it and records the
    largest such reach."""
    w = coc.shape[1]
    for x in range(w):
        c0 = coc[y, x]
        if c0 >= 0.0 or not ecc[y, x] < r1:
            continue
        far[y, x, 0], far[y, x, 1], far[y, x, 2] = _far_gauss(color, color, ecc, coc, y, x, 0, 1, r1, c0)
    if not has_near:
        return
    for x in range(w):
        n = reach = r = g = b = 0.0
        for xx in range(max(0, x - radius), min(w, x + radius + 1)):
            c = coc[y, xx]
            if c > 0.0 and abs(xx - x) <= c:
                n += 1.0
                reach = max(reach, min(c, MAX_BLUR_PX))
                r, g, b = r + color[y, xx, 0], g + color[y, xx, 1], b + color[y, xx, 2]
        if n > 0.0:
            near[y, x, 0], near[y, x, 1], near[y, x, 2] = r / n, g / n, b / n
        near[y, x, 3] = reach


@kernel
def _horizontal(color, ecc, layers, blur, counter, threads):
    """Rows claimed (hmdrt.kernels.schedule): the near field's rows, at the bottom of the image, cost several times
    more."""
    coc, far, near, rows = layers.coc, layers.far, layers.near, layers.rows
    r1, radius = blur.r1, blur.radius
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < coc.shape[0]:
            _horizontal_row(color, ecc, coc, far, near, y, r1, radius, rows[y, ROW_MAX] > 0.0)
            y = claim(counter)


@inline
def _near_vertical(near, rows, y, x, radius):
    """The near field's second pass: the average over the rows whose reach covers this pixel, and the
    coverage: those rows over the disc's full diameter (1 inside a near object, falling off at its edge)."""
    n = reach = r = g = b = 0.0
    for yy in range(max(0, y - radius), min(near.shape[0], y + radius + 1)):
        if rows[yy, ROW_MAX] <= 0.0:  # no near-field pixel in that row: no reach anywhere along it
            continue
        c = near[yy, x, 3]
        if c > 0.0 and abs(yy - y) <= c:
            n += 1.0
            reach = max(reach, c)
            r, g, b = r + near[yy, x, 0], g + near[yy, x, 1], b + near[yy, x, 2]
    if n == 0.0:
        return 0.0, 0.0, 0.0, 0.0
    return r / n, g / n, b / n, min(1.0, n / (2.0 * reach + 1.0))


@serial
def _periphery(e, r0, r1):
    """How far into the periphery's pyramid blur the far field is at eccentricity e: 0 inside r0, 1 from r1."""
    return 0.0 if e < r0 else (1.0 if e >= r1 or r1 <= r0 else (e - r0) / (r1 - r0))


@serial
def _dof_row(color, ecc, layers, blur, pyramid, axes, levels, values, texels, runs, y, out):
    """Row y of the second pass. Far field: the central Gaussian, the pyramid blur in the periphery (read at
    level log2 |CoC| for the row at once, sample_row, into values), blended across [r0, r1); the sharp image
    is interpolated towards it by |CoC|; the near field is alpha-blended over."""
    coc, far, near, rows = layers
    r0, r1, ramp, radius = blur
    near_rows = False  # whether a row within reach holds the near field: else no pixel of this one is covered
    for yy in range(max(0, y - radius), min(coc.shape[0], y + radius + 1)):
        near_rows |= rows[yy, ROW_MAX] > 0.0
    for x in range(out.shape[1]):
        c = coc[y, x]
        read = c < 0.0 and _periphery(ecc[y, x], r0, r1) > 0.0
        levels[x] = (0.0 if -c <= 1.0 else math.log2(-c)) if read else -1.0
    sample_row(pyramid.data, pyramid.widths, axes, y, levels, values, texels, runs)
    for x in range(out.shape[1]):
        c = coc[y, x]
        r, g, b = color[y, x, 0], color[y, x, 1], color[y, x, 2]
        if c < 0.0:
            e = ecc[y, x]
            blend = _periphery(e, r0, r1)
            if e < r1:
                fr, fg, fb = _far_gauss(far, color, ecc, coc, y, x, 1, 0, r1, c)  # beyond r1 no first pass ran
            else:
                fr, fg, fb = r, g, b
            if blend > 0.0:
                pr, pg, pb = values[x, 0], values[x, 1], values[x, 2]
                fr, fg, fb = fr + blend * (pr - fr), fg + blend * (pg - fg), fb + blend * (pb - fb)
            t = min(1.0, -c / ramp)
            r, g, b = r + t * (fr - r), g + t * (fg - g), b + t * (fb - b)
        if near_rows:
            nr, ng, nb_, a = _near_vertical(near, rows, y, x, radius)
            if a > 0.0:
                r, g, b = r + a * (nr - r), g + a * (ng - g), b + a * (nb_ - b)
        out[y, x, 0], out[y, x, 1], out[y, x, 2] = r, g, b


@serial
def _copy_row(level, y, out):
    """Row y of a pyramid level's colour into out, the rows flattened so that the strides are constants: the loop
    vectorises."""
    rgb, src = out[y].reshape(-1), level[y].reshape(-1)
    for x in range(out.shape[1]):
        rgb[3 * x], rgb[3 * x + 1], rgb[3 * x + 2] = src[CHANNELS * x], src[CHANNELS * x + 1], src[CHANNELS * x + 2]


@kernel
def _combine(color, ecc, layers, blur, pyramid, contrast, blurred, axes, scratch, dof, out, counter, threads):
    """Row by row, the depth of field then the contrast over the row while it is in cache: two simple loops
    compile to faster code than one that does both. Without depth of field the contrast enhancement reads the sharp
    colour and writes the row (no copy first). Rows claimed (hmdrt.kernels.schedule): their cost varies."""
    for _ in nb.prange(threads):
        thread = nb.get_thread_id()
        levels, values, texels, runs = (
            scratch.levels[thread],
            scratch.values[thread],
            scratch.texels[thread],
            scratch.runs[thread],
        )
        y = claim(counter)
        while y < out.shape[0]:
            if dof:
                _dof_row(color, ecc, layers, blur, pyramid, axes, levels, values, texels, runs, y, out)
                if contrast.strength != 0.0:
                    row = out[y].reshape(-1)  # one array in and out: the compiler sees the loop work in place
                    enhance_row(ecc, contrast, blurred, axes, values, texels, runs, row, 3, y, row)
            elif contrast.strength != 0.0:  # the sharp colour enhanced as it is copied
                row = color[y].reshape(-1)
                enhance_row(ecc, contrast, blurred, axes, values, texels, runs, row, CHANNELS, y, out[y].reshape(-1))
            else:
                _copy_row(color, y, out)
            y = claim(counter)


def horizontal_pass(color: np.ndarray, ecc: np.ndarray, layers: Layers, blur: Blur) -> None:
    """The first pass of the layered blur (layers.coc and its rows computed) over the colour of `color`
    (height, width, 3 or more; best a pyramid level, read in place): into layers.far and layers.near."""
    dynamic(_horizontal, color, ecc, layers, blur)


def combine(
    color: np.ndarray,
    ecc: np.ndarray,
    layers: Layers | None,
    blur: Blur,
    pyramid: Pyramid,
    contrast: Contrast,
    blurred: Pyramid,
    axes: PixelAxes,
    scratch: RowSamples,
    out: np.ndarray,
) -> np.ndarray:
    """weier2018's DoF Combine in one pass over the image, into out: the second pass of the layered blur
    and its combination with the sharp image when layers are given (after horizontal_pass), then the
    contrast enhancement (filters.enhance_row, from `blurred`, the pyramid prefiltered by filters.prefilter;
    strength 0: none). `color`: the sharp image, best a pyramid level (height, width, CHANNELS), read in place
    (_as_level); `axes`: the pixel_axes of both pyramids' size; `scratch`: RowSamples of their width; `out`:
    C-contiguous (height, width, 3)."""
    no_layers = layers is None
    layers = _NO_LAYERS if no_layers else layers
    level = _as_level(color)
    dynamic(_combine, level, ecc, layers, blur, pyramid, contrast, blurred, axes, scratch, not no_layers, out)
    return out


def _as_level(color: np.ndarray) -> np.ndarray:
    """color (height, width, 3 or more) as the C-contiguous (height, width, CHANNELS) array of a pyramid level that
    the combine's row loops read with constant strides (so that they vectorise): itself when it is one, else a
    copy (a caller other than a pyramid's, once per call)."""
    if color.shape[2] == CHANNELS and color.flags.c_contiguous:
        return color
    level = np.zeros((*color.shape[:2], CHANNELS), color.dtype)
    level[..., :3] = color[..., :3]
    return level


_NO_LAYERS = Layers.empty(0, 0)


def layered_blur(
    color: np.ndarray, coc: np.ndarray, ecc: np.ndarray, r0: float, r1: float, pyramid: Pyramid, ramp: float = RAMP_PX
) -> np.ndarray:
    """The depth-of-field image: layered near / focused / far blur with the CoC map (pixels, signed)."""
    h, w = coc.shape
    layers = Layers.empty(w, h)
    layers.coc[:] = coc
    _coc_stats(layers.coc, layers.rows)
    blur = Blur(r0, r1, ramp, layers.near_radius())
    horizontal_pass(color, ecc, layers, blur)
    no_contrast = Contrast(0.0, r0, r1, np.zeros((0, 0), np.float32))
    axes, scratch = pixel_axes(pyramid), RowSamples.empty(w)
    return combine(color, ecc, layers, blur, pyramid, no_contrast, pyramid, axes, scratch, np.empty_like(color))


def gaze_depth(
    depth_m: np.ndarray,
    por: np.ndarray,
    ppd: float,
    vergence_m: float | None,
    radius_deg: float = 1.0,
    miss: float = math.inf,
) -> float:
    """The focused depth: depth samples at and around the point of regard (weier2018 Figure 4, a centre
    and eight points on a ring), the one nearest the vergence depth when the two eyes' gaze gives one,
    else their median. Depths at or beyond `miss` are misses. (The paper feeds these measures to a per-user
    trained SVM; this is its stand-in.)"""
    h, w = depth_m.shape
    angles = np.linspace(0.0, 2 * np.pi, 8, endpoint=False)
    r = radius_deg * ppd
    xs = np.concatenate([[por[0]], por[0] + r * np.cos(angles)])
    ys = np.concatenate([[por[1]], por[1] + r * np.sin(angles)])
    inside = (xs >= 0) & (xs < w) & (ys >= 0) & (ys < h)
    samples = depth_m[ys[inside].astype(int), xs[inside].astype(int)]
    samples = samples[samples < miss]
    if len(samples) == 0:
        return vergence_m if vergence_m is not None else 1e3
    if vergence_m is not None and math.isfinite(vergence_m):
        return float(samples[np.argmin(np.abs(samples - vergence_m))])
    return float(np.median(samples))
