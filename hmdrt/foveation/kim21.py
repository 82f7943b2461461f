"""Selective foveated supersampling with Whitted ray tracing (kim2021).

Section 4.3: every pixel is presampled at its centre, gathering the attributes of Table 1 (colour;
object id, normal, shadow count and texture existence at the primary and first secondary hit).
Section 4.1: eccentricity bands e_f, e_p, e_m, e_np (3.3, 5.5, 12.1, 30 deg) split the central
region (e < e_np, supersampled) from the periphery (one sample per pixel). Section 4.4: the pixel
reusability test copies a pixel from the previous frame when its back-projected first hit agrees
(at most n_reuse_max times in a row). Sections 3 and 4.6.1: the two-step disparity test per 2x2
subpixel: geometry discordance with any of the three neighbours selects tau_sel, then Mitchell's
contrast is compared with (1.36, 1.02, 2.04) x tau_fov(e) x tau_sel, tau_fov from two C1 quadratic
Bezier segments. Section 4.6.2: problematic subpixels take (n_f, n_p, n_m, n_np) stratified jittered
samples by band; in every central pixel rendered, the others take the colour interpolated from the
four surrounding pixel centres (Figure 2), or with interpolate=false the presampled colour as in Jin
et al.'s selective supersampling. Section 4.7: temporal smoothing over up to 4 back-projected earlier
frames with alpha(e) piecewise linear through 0.9, 0.8, 0.7, 0.5, 0.2, 0.1 at 0, e_f, e_p, e_m, e_np,
e_max.

The paper leaves open when two normals disagree; here, when their dot product is below normal_cos.
Reuse also needs the copied colour rendered at no lower class (samples per problematic subpixel) than
the pixel needs now, or a saccade copies one-sample colours into the new fovea, and where the colour was
sampled may drift at most reuse_px pixels over the chain of copies (docs/methods.md, kim21, says why).
The supersampling jitter is fixed per subpixel across frames: with a still view the frames agree,
and temporal smoothing works on what the paper targets, the noise of the received poses (Table 3).
"""

from __future__ import annotations

import math
from typing import Annotated, NamedTuple

import msgspec
import numba as nb
import numpy as np

from hmdrt.errors import ConfigError
from hmdrt.foveation.base import HISTORY, Configurable, FrameRequest, Knob, Stage, pixel_keys, plan
from hmdrt.foveation.stages.temporal import (
    History,
    exponential_smoothing,
    eye_point,
    relative_view,
    same_camera,
    view_project,
)
from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.schedule import claim, dynamic
from hmdrt.optics.camera import EyeCamera, eccentricity_map, pixel_grid
from hmdrt.optics.projection import FAR, bilinear3, camera_arrays, nearest_index
from hmdrt.ranges import Deg
from hmdrt.telemetry.stats import FrameStats, nbytes
from hmdrt.trace.gbuffer import GBuffer
from hmdrt.trace.integrator import Whitted
from hmdrt.trace.sampling import DIM_PIXEL, grid_dims, stratified

Positive = Annotated[float, msgspec.Meta(gt=0.0, le=1e3)]
Threshold = Annotated[float, msgspec.Meta(ge=0.0, le=10.0)]
Samples = Annotated[int, msgspec.Meta(ge=1, le=16)]
Weight = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]  # a blending factor: above 1, (1 - a)^i changes sign
MAX_SUBPIXEL_SAMPLES = 16


class Kim21Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    # eccentricity bands (section 4.1)
    e_f: Deg = 3.3
    e_p: Deg = 5.5
    e_m: Deg = 12.1
    e_np: Deg = 30.0
    e_max: Deg = 45.0
    # samples per problematic subpixel by band (section 4.6.2)
    n_f: Samples = 9
    n_p: Samples = 4
    n_m: Samples = 2
    n_np: Samples = 1
    # tau_fov shape (tau_0, tau_f, tau_f', tau_np), Figure 7's tau^1
    tau_0: Positive = 1.0
    tau_f: Positive = 2.0
    tau_f_slope: Annotated[float, msgspec.Meta(ge=0.0, le=1e3)] = 0.5
    tau_np: Positive = 12.0
    # Table 1 thresholds, with Figure 6's values
    tau_col: Threshold = 0.02
    tau_poid: Threshold = 0.05
    tau_psn: Threshold = 0.06
    tau_psc: Threshold = 0.06
    tau_pte: Threshold = 0.02
    tau_soid: Threshold = 0.02
    tau_ssn: Threshold = 0.02
    tau_ssc: Threshold = 0.06
    tau_ste: Threshold = 0.02
    normal_cos: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)] = 0.95
    # the colour of a non-problematic subpixel: interpolated from the four surrounding pixel centres (kim2021,
    # Figure 2), or the pixel's own presampled colour as in Jin et al.'s selective supersampling
    interpolate: bool = True
    # pixel reuse (section 4.4) and temporal smoothing (section 4.7)
    reuse: bool = True
    n_reuse_max: Annotated[int, msgspec.Meta(ge=0, le=1000)] = 5
    tau_reuse: Threshold = 1.0
    reuse_px: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.1  # how far a reused colour may drift, pixels
    smooth: bool = True
    smooth_frames: Annotated[int, msgspec.Meta(ge=0, le=4)] = 4
    alpha: tuple[Weight, Weight, Weight, Weight, Weight, Weight] = (0.9, 0.8, 0.7, 0.5, 0.2, 0.1)
    depth_tolerance: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.02  # relative, for reuse and smoothing

    def __post_init__(self) -> None:
        if not self.e_f <= self.e_p <= self.e_m <= self.e_np <= self.e_max:
            raise ValueError("the bands need e_f <= e_p <= e_m <= e_np <= e_max")


def bezier_controls(p: Kim21Params) -> np.ndarray:
    """Control points of tau_fov's two quadratic Bezier segments, as [x0, x1, x2, y0, y1, y2] x 2.

    C1 runs from (0, tau_0) to (e_f, tau_f) with slope 0 then tau_f'; C2 from (e_f, tau_f) to
    (e_np, tau_np) with slope tau_f' then 0. Each middle control point is where the end tangents
    cross; it must lie between the end points in e so that tau_fov is a function of e.
    """

    def middle(x0: float, y0: float, s0: float, x2: float, y2: float, s2: float) -> float:
        if y0 == y2:
            return 0.5 * (x0 + x2)  # a flat segment: any middle point on the line
        slope = s2 if s0 == 0.0 else s0
        if slope == 0.0:
            raise ConfigError("tau_f_slope must be positive unless tau_0, tau_f and tau_np are equal")
        return x2 - (y2 - y0) / slope if s0 == 0.0 else x0 + (y2 - y0) / slope

    m1 = middle(0.0, p.tau_0, 0.0, p.e_f, p.tau_f, p.tau_f_slope)
    m2 = middle(p.e_f, p.tau_f, p.tau_f_slope, p.e_np, p.tau_np, 0.0)
    if not (0.0 <= m1 <= p.e_f and p.e_f <= m2 <= p.e_np):
        raise ConfigError(
            f"tau_fov shape (tau_0={p.tau_0}, tau_f={p.tau_f}, tau_f'={p.tau_f_slope}, tau_np={p.tau_np}) "
            "does not give a function of eccentricity: the tangents must meet between the band edges"
        )
    return np.array([0.0, m1, p.e_f, p.tau_0, p.tau_0, p.tau_f, p.e_f, m2, p.e_np, p.tau_f, p.tau_np, p.tau_np])


MITCHELL = (1.36, 1.02, 2.04)  # kim2021 section 3: the contrast threshold vector per tau
MAX_SMOOTH_FRAMES = 4  # section 4.7: up to four earlier frames


class Foveation(NamedTuple):
    """What kim21 derives per pixel from its eccentricity e, once per change of the frustum, gaze or parameters."""

    samples: np.ndarray  # (n,) uint8 samples per problematic subpixel in e's band (section 4.6.2); 0 beyond e_np
    tau_fov: np.ndarray  # (n,) float64 tau_fov(e) (section 4.6.1)
    alpha: np.ndarray  # (n,) float32 smoothing factor alpha(e) (section 4.7)

    @classmethod
    def empty(cls, n: int) -> Foveation:
        return cls(np.empty(n, np.uint8), np.empty(n), np.empty(n, np.float32))


class Tests(NamedTuple):
    """The thresholds of the disparity and reusability tests (Table 1; sections 4.4 and 4.6.1)."""

    thresholds: np.ndarray  # (9,) tau_col, then object id, normal, shadow count, texture at the primary, secondary hit
    normal_cos: float
    tau_reuse: float
    n_reuse_max: int
    rel_depth: float
    reuse_px: float


class Kept(NamedTuple):
    """A frame's buffers that the next frame reads: presampled colour, hit distance, reuse count, rendered colour,
    and what the rendered colour is worth to a later reuse: its class and where it was sampled."""

    ref: np.ndarray  # (n, 3) float32 the presampled colour at the pixel centres
    depth: np.ndarray  # (n,) float32 the history's depth slot: distance of the first hit, inf on a miss
    flags: np.ndarray  # (n,) int32 times in a row the pixel was reused; 0 where rendered
    rendered: np.ndarray  # (n, 3) float32 the history's colour slot, before smoothing
    level: np.ndarray  # (n,) uint8 samples per problematic subpixel the colour was rendered with; 0 outside e_np
    drift: np.ndarray  # (n, 2) float32 where the colour was rendered, in pixels from the pixel centre


@serial
def _bezier_y_at_x(x0, x1, x2, y0, y1, y2, e):
    """y of the quadratic Bezier at the parameter where x(t) = e; the linear case when a = 0."""
    a = x0 - 2.0 * x1 + x2
    b = 2.0 * (x1 - x0)
    c = x0 - e
    if abs(a) < 1e-12 * max(abs(b), 1e-300):
        t = -c / b if b != 0.0 else 0.0
    else:
        disc = max(b * b - 4.0 * a * c, 0.0)
        q = -0.5 * (b + math.copysign(math.sqrt(disc), b))
        t1 = q / a
        t2 = c / q if q != 0.0 else t1
        t = t1 if -1e-9 <= t1 <= 1.0 + 1e-9 else t2
    t = min(max(t, 0.0), 1.0)
    u = 1.0 - t
    return u * u * y0 + 2.0 * u * t * y1 + t * t * y2


@inline
def tau_fov(e, ctrl):
    """kim2021's tau_fov(e): y1(x1^-1(e)) on [0, e_f], y2(x2^-1(e)) on (e_f, e_np], tau_np beyond."""
    if e <= ctrl[2]:
        return _bezier_y_at_x(ctrl[0], ctrl[1], ctrl[2], ctrl[3], ctrl[4], ctrl[5], max(e, 0.0))
    if e <= ctrl[8]:
        return _bezier_y_at_x(ctrl[6], ctrl[7], ctrl[8], ctrl[9], ctrl[10], ctrl[11], e)
    return ctrl[11]


@serial
def tau_fov_array(e, ctrl):
    out = np.empty(e.shape[0])
    for i in range(e.shape[0]):
        out[i] = tau_fov(e[i], ctrl)
    return out


def alpha_knots(p: Kim21Params) -> np.ndarray:
    """The eccentricities where alpha(e) takes p.alpha: 0, e_f, e_p, e_m, e_np, e_max."""
    return np.array([0.0, p.e_f, p.e_p, p.e_m, p.e_np, p.e_max])


def alpha_of_eccentricity(ecc: np.ndarray, p: Kim21Params) -> np.ndarray:
    """alpha(e), piecewise linear through p.alpha at alpha_knots, constant beyond."""
    return np.interp(ecc, alpha_knots(p), p.alpha).astype(np.float32)


@serial
def _foveation_row(y, ecc, ctrl, bounds, counts, e_np, alpha_x, alpha_y, fov):
    samples, tau, alpha = fov
    width = ecc.shape[1]
    central = 0
    for x in range(width):
        i = y * width + x
        e = ecc[y, x]
        band = 0
        while band < 3 and e >= bounds[band]:
            band += 1
        inside = e < e_np
        samples[i] = counts[band] if inside else 0
        central += inside
        tau[i] = tau_fov(e, ctrl)
        alpha[i] = np.interp(e, alpha_x, alpha_y)
    return central


@kernel
def _foveation(ecc, ctrl, bounds, counts, e_np, alpha_x, alpha_y, fov):
    """Every pixel's Foveation from the eccentricity map ecc (h, w); returns the number of central pixels (e < e_np)."""
    central = 0
    for y in nb.prange(ecc.shape[0]):
        central += _foveation_row(y, ecc, ctrl, bounds, counts, e_np, alpha_x, alpha_y, fov)
    return central


@serial
def _contrast_fails(color, a, b, c, d, tau):
    """Mitchell's contrast (max - min) / (max + min) of rows a, b, c, d of color (n, 3), per channel,
    against tau x (1.36, 1.02, 2.04)."""
    for ch in range(3):
        va, vb, vc, vd = color[a, ch], color[b, ch], color[c, ch], color[d, ch]
        lo, hi = min(min(va, vb), min(vc, vd)), max(max(va, vb), max(vc, vd))
        if hi + lo > 0.0 and (hi - lo) / (hi + lo) > MITCHELL[ch] * tau:
            return True
    return False


@serial
def _pair_contrast_fails(color_a, i, color_b, j, tau):
    """Mitchell's contrast between pixel i of color_a and pixel j of color_b."""
    for ch in range(3):
        va, vb = color_a[i, ch], color_b[j, ch]
        lo, hi = min(va, vb), max(va, vb)
        if hi + lo > 0.0 and (hi - lo) / (hi + lo) > MITCHELL[ch] * tau:
            return True
    return False


@inline
def _geometry(hits):
    """The attributes of Table 1's geometry tests as a plain tuple (object id, normal, shadow count, texture): row
    functions take them out of the G-buffer once, since every namedtuple a helper receives costs a reference count
    per array."""
    return hits.object_id, hits.normal_shading, hits.shadow_count, hits.textured


@inline
def _discordant_threshold(a, i, b, j, thresholds, first, normal_cos):
    """The smallest of thresholds[first:first + 4] over the attributes (object id, normal, shadow count, texture)
    on which hit i of geometry a and hit j of geometry b disagree, inf when they agree on all (Table 1). Normals
    disagree when both are hits and their dot product is below normal_cos."""
    obj_a, ns_a, shadow_a, tex_a = a
    obj_b, ns_b, shadow_b, tex_b = b
    tau = math.inf
    if obj_a[i] != obj_b[j]:
        tau = thresholds[first]
    dot = ns_a[i, 0] * ns_b[j, 0] + ns_a[i, 1] * ns_b[j, 1] + ns_a[i, 2] * ns_b[j, 2]
    if obj_a[i] >= 0 and obj_b[j] >= 0 and dot < normal_cos:
        tau = min(tau, thresholds[first + 1])
    if shadow_a[i] != shadow_b[j]:
        tau = min(tau, thresholds[first + 2])
    if tex_a[i] != tex_b[j]:
        tau = min(tau, thresholds[first + 3])
    return tau


@inline
def _tau_sel(i, a, b, c, primary, secondary, thresholds, normal_cos):
    """Step one of a subpixel's disparity test: the smallest threshold over the geometry attributes on which
    pixel i disagrees with neighbour a, b or c at the primary or the secondary hit; tau_col when it agrees."""
    tau = math.inf
    for j in (a, b, c):
        tau = min(tau, _discordant_threshold(primary, i, primary, j, thresholds, 1, normal_cos))
        tau = min(tau, _discordant_threshold(secondary, i, secondary, j, thresholds, 5, normal_cos))
    return thresholds[0] if tau == math.inf else tau


@serial
def _store_row(y, width, color, hits, frustum, frame, view, prev_hits, prev, same, tests, reuse, samples):
    """Row y of `frame`, rendered as presampled (color, hits) at its band's class `samples`; with `reuse`, kim2021
    section 4.4's test per central pixel with a hit: back-projected into the previous frame (through its relative_view
    `view`; onto itself when `same`) it must meet a hit within rel_depth of its distance, reused fewer than n_reuse_max
    times in a row and rendered at no lower class than the pixel needs now, that agrees in the primary attributes and
    passes the contrast test at tau_sel x tau_reuse, with the drift of where its colour was sampled staying within
    reuse_px; it takes that pixel's rendered colour, class and drift then. Returns the row's reused pixels."""
    ref, depth, flags, rendered, level, drift = frame
    prev_ref, prev_depth, prev_flags, prev_rendered, prev_level, prev_drift = prev
    hit_depth, geometry, prev_geometry = hits.depth, _geometry(hits), _geometry(prev_hits)
    obj, prev_obj = geometry[0], prev_geometry[0]
    thresholds, normal_cos, tau_reuse, n_max, rel_depth, reuse_px = tests
    height = depth.shape[0] // width
    reused = 0
    for x in range(width):
        i = y * width + x
        d = hit_depth[i]
        depth[i] = d
        for c in range(3):
            ref[i, c] = color[i, c]
            rendered[i, c] = color[i, c]
        flags[i], level[i] = 0, samples[i]
        drift[i, 0] = drift[i, 1] = 0.0
        if not reuse or samples[i] == 0 or math.isinf(d) or obj[i] < 0:
            continue
        j, dist, ox, oy = i, min(np.float64(d), FAR), 0.0, 0.0
        if not same:
            px, py, pz = eye_point(frustum, x + 0.5, y + 0.5, d)
            qx, qy, dist = view_project(view, px, py, pz)
            j = nearest_index(qx, qy, width, height)
            ox, oy = qx - (j % width + 0.5), qy - (j // width + 0.5)
        if j < 0 or prev_flags[j] >= n_max or prev_level[j] < samples[i]:
            continue
        if math.isinf(prev_depth[j]) or prev_obj[j] < 0 or abs(prev_depth[j] - dist) > rel_depth * dist:
            continue
        dx, dy = prev_drift[j, 0] - ox, prev_drift[j, 1] - oy
        if dx * dx + dy * dy > reuse_px * reuse_px:
            continue
        tau = _discordant_threshold(geometry, i, prev_geometry, j, thresholds, 1, normal_cos)
        tau = thresholds[0] if tau == math.inf else tau
        if _pair_contrast_fails(color, i, prev_ref, j, tau * tau_reuse):
            continue
        flags[i], level[i] = prev_flags[j] + 1, prev_level[j]
        drift[i, 0], drift[i, 1] = dx, dy
        for c in range(3):
            rendered[i, c] = prev_rendered[j, c]
        reused += 1
    return reused


@serial
def _clear_row(y, width, hits):
    obj, ns, shadow, tex = _geometry(hits)
    for i in range(y * width, (y + 1) * width):
        obj[i] = -1
        ns[i, 0] = ns[i, 1] = ns[i, 2] = 0.0
        shadow[i] = 0
        tex[i] = False


@kernel
def _clear(width, hits):
    """Every hit a miss in the attributes the tests read (the tracer fills the secondary hits it finds)."""
    for y in nb.prange(hits.object_id.shape[0] // width):
        _clear_row(y, width, hits)


@kernel
def _store(width, color, hits, frustum, frame, view, prev_hits, prev, same, tests, reuse, samples, counter, threads):
    """_store_row over the image, rows claimed (hmdrt.kernels.schedule: a row of reused pixels costs more); returns the
    number of reused pixels."""
    reused = 0
    h = frame.depth.shape[0] // width
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < h:
            reused += _store_row(
                y, width, color, hits, frustum, frame, view, prev_hits, prev, same, tests, reuse, samples
            )
            y = claim(counter)
    return reused


@serial
def _box_contrast_row(y, width, ref, tau_fov, bound, box, passes):
    """passes[x] = whether Mitchell's contrast of the 3x3 box around pixel (x, y) of ref (n, 3), clamped to the
    image, stays within bound x tau_fov x (1.36, 1.02, 2.04) in every channel, with a margin over float32 rounding.
    A 2x2 subpixel block inside the box has no more contrast (it grows with max, falls with min, for non-negative
    colours), so it passes too. Separably, in loops that vectorise (unsigned indices: no negative-index wraparound;
    selects, no branches): each column's three rows into box (lowest and highest per channel, 6 rows of the row's
    width + 2, the edge columns repeated either side), then three columns of those."""
    height, u, one, two = ref.shape[0] // width, np.uint64, np.uint64(1), np.uint64(2)
    flat = ref.reshape(-1)
    top, mid, bottom = max(y - 1, 0) * width, y * width, min(y + 1, height - 1) * width
    for x in range(width):
        passes[x] = True
    for ch in range(3):
        lo, hi, scale = box[ch], box[3 + ch], MITCHELL[ch]
        t, m, b = u(3 * top + ch), u(3 * mid + ch), u(3 * bottom + ch)
        for x in range(width):
            k = u(3 * x)
            va, vb, vc = np.float64(flat[t + k]), np.float64(flat[m + k]), np.float64(flat[b + k])
            lo[u(x) + one], hi[u(x) + one] = min(min(va, vb), vc), max(max(va, vb), vc)
        lo[0], hi[0], lo[width + 1], hi[width + 1] = lo[1], hi[1], lo[width], hi[width]
        for x in range(width):
            i = u(x)
            low, high = min(min(lo[i], lo[i + one]), lo[i + two]), max(max(hi[i], hi[i + one]), hi[i + two])
            spread = np.divide(high - low, high + low) * (1.0 + 1e-6)
            fails = (low < 0.0) | ((high + low > 0.0) & (spread > scale * (bound * tau_fov[u(mid) + i])))
            passes[i] = passes[i] & (not fails)


@serial
def _inspect_row(y, width, ref, primary, secondary, fov, flags, tests, sub_mask, box, passes):
    """Row y of the two-step disparity test of every subpixel of every central pixel not reused: the 4-bit mask of
    the problematic subpixels (NW, NE, SW, SE). A subpixel whose contrast passes at the smallest threshold passes
    at tau_sel too, so step one runs only where the contrast is high enough to matter, and a pixel whose 3x3
    neighbourhood passes there is done. Returns the row's extra samples and problematic subpixels."""
    height = flags.shape[0] // width
    p, s2 = _geometry(primary), _geometry(secondary)
    thresholds, normal_cos = tests.thresholds, tests.normal_cos
    counts, tau_fov_ = fov.samples, fov.tau_fov
    lowest = thresholds.min()
    _box_contrast_row(y, width, ref, tau_fov_, lowest, box, passes)
    samples = subpixels = 0
    for x in range(width):
        i = y * width + x
        sub_mask[i] = 0
        k = np.int64(counts[i])
        if k == 0 or flags[i] != 0 or passes[x]:
            continue
        tau_f = tau_fov_[i]
        mask = 0
        for s in range(4):
            dx = -1 if s & 1 == 0 else 1
            dy = -1 if s < 2 else 1
            nx, ny = min(max(x + dx, 0), width - 1), min(max(y + dy, 0), height - 1)
            a, b, c = y * width + nx, ny * width + x, ny * width + nx
            if not _contrast_fails(ref, i, a, b, c, lowest * tau_f):
                continue
            tau = _tau_sel(i, a, b, c, p, s2, thresholds, normal_cos) * tau_f
            if _contrast_fails(ref, i, a, b, c, tau):
                mask |= 1 << s
                samples += k
                subpixels += 1
        sub_mask[i] = mask
    return samples, subpixels


@kernel
def _inspect(width, ref, primary, secondary, fov, flags, tests, sub_mask, row_samples, box, passes):
    """_inspect_row over the image: row_samples[y] = row y's extra samples; returns the problematic subpixels. box and
    passes: _box_contrast_row's scratch, a row per numba thread (nb.get_thread_id())."""
    subpixels = 0
    for y in nb.prange(flags.shape[0] // width):
        t = nb.get_thread_id()
        row_samples[y], sub = _inspect_row(
            y, width, ref, primary, secondary, fov, flags, tests, sub_mask, box[t], passes[t]
        )
        subpixels += sub
    return subpixels


@serial
def _exclusive_scan(counts):
    """counts[k] becomes the sum of counts[:k], in place; returns the total."""
    total = 0
    for k in range(counts.shape[0]):
        c = counts[k]
        counts[k] = total
        total += c
    return total


@serial
def _subpixel_samples_row(y, width, sub_mask, samples, first, seed_key, xy, keys):
    j = first[y]
    for x in range(width):
        i = y * width + x
        m = sub_mask[i]
        if m == 0:
            continue
        n = np.int64(samples[i])
        nx, ny = grid_dims(n)
        for s in range(4):
            if not (m >> s) & 1:
                continue
            ox, oy = x + 0.5 * (s & 1), y + 0.5 * (s >> 1)
            key = (i * 4 + s) * MAX_SUBPIXEL_SAMPLES + seed_key
            for k in range(n):
                sx, sy = stratified(key, k, DIM_PIXEL, nx, ny)
                xy[j, 0] = ox + 0.5 * sx
                xy[j, 1] = oy + 0.5 * sy
                keys[j] = key + k
                j += 1


@kernel
def _subpixel_samples(width, sub_mask, samples, first, seed_key, xy, keys):
    """Stratified jittered positions of the extra samples, subpixel by subpixel in scanline order (section 4.6.2);
    row y's start at first[y]."""
    for y in nb.prange(first.shape[0] - 1):
        _subpixel_samples_row(y, width, sub_mask, samples, first, seed_key, xy, keys)


@serial
def _mean3(rows, start, count):
    """The mean of rows [start, start + count) of an (n, 3) array."""
    r = g = b = 0.0
    for j in range(start, start + count):
        r, g, b = r + rows[j, 0], g + rows[j, 1], b + rows[j, 2]
    return r / count, g / count, b / count


@serial
def _tent(up, mid, down, x, ch):
    """Channel ch of the mean of pixel x's four subpixels, each interpolated from the four surrounding pixel
    centres (kim2021 Figure 2), given its row and the rows above and below (w, 3), clamped at the border as
    bilinear3 is: bilinear weights 3/4 and 1/4 per axis average to (1, 6, 1) / 8 over the 3 x 3 neighbourhood."""
    a, c = np.float32(0.125), np.float32(0.75)
    xl, xr = max(x - 1, 0), min(x + 1, mid.shape[0] - 1)
    left = a * (up[xl, ch] + down[xl, ch]) + c * mid[xl, ch]
    centre = a * (up[x, ch] + down[x, ch]) + c * mid[x, ch]
    right = a * (up[xr, ch] + down[xr, ch]) + c * mid[xr, ch]
    return a * (left + right) + c * centre


@serial
def _subpixel_color(image, x, y, s, interpolate):
    """Subpixel s (NW, NE, SW, SE) of pixel (x, y) when not problematic: interpolated at its centre from the four
    surrounding pixel centres (kim2021 Figure 2), or the pixel's presampled colour (Jin et al.)."""
    if interpolate:
        return bilinear3(image, x + 0.25 + 0.5 * (s & 1), y + 0.25 + 0.5 * (s >> 1))
    return np.float64(image[y, x, 0]), np.float64(image[y, x, 1]), np.float64(image[y, x, 2])


@serial
def _resolve_row(y, image, sub_mask, samples, flags, first, extra, interpolate, out):
    height, width, y = image.shape[0], image.shape[1], np.int64(y)
    up, mid, down = image[max(y - 1, 0)], image[y], image[min(y + 1, height - 1)]
    j = first[y]
    for x in range(width):
        i = y * width + x
        if samples[i] == 0 or flags[i] != 0:
            continue
        m, k = sub_mask[i], np.int64(samples[i])
        if m == 0:
            for ch in range(3 if interpolate else 0):
                out[i, ch] = _tent(up, mid, down, x, ch)
            continue
        r = g = b = 0.0
        for s in range(4):
            if (m >> s) & 1:
                cr, cg, cb = _mean3(extra, j, k)
                j += k
            else:
                cr, cg, cb = _subpixel_color(image, x, y, s, interpolate)
            r, g, b = r + cr, g + cg, b + cb
        out[i, 0], out[i, 1], out[i, 2] = 0.25 * r, 0.25 * g, 0.25 * b


@kernel
def _resolve(image, sub_mask, samples, flags, first, extra, interpolate, out, counter, threads):
    """Section 4.6.2 and Figure 2: each central pixel that was rendered (flags 0) is the mean of its four subpixels,
    a problematic one the mean of its extra samples, the others their _subpixel_color from the presampled colours
    (image, (h, w, 3)); out already holds the presampled colour, which stays where nothing is interpolated."""
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < image.shape[0]:
            _resolve_row(y, image, sub_mask, samples, flags, first, extra, interpolate, out)
            y = claim(counter)


class _Buffers(NamedTuple):
    """A frame's G-buffer, presampled colour, reuse counts, classes and drifts, which the next frame's reuse test
    reads (Kept)."""

    gbuffer: GBuffer
    ref: np.ndarray  # (n, 3) float32
    flags: np.ndarray  # (n,) int32
    level: np.ndarray  # (n,) uint8
    drift: np.ndarray  # (n, 2) float32

    @classmethod
    def empty(cls, n: int) -> _Buffers:
        ref, flags = np.empty((n, 3), np.float32), np.zeros(n, np.int32)
        return cls(GBuffer.empty(n), ref, flags, np.zeros(n, np.uint8), np.zeros((n, 2), np.float32))


class _EyeState:
    """One eye's buffers at one image size, persistent across frames."""

    def __init__(self, height: int, width: int, smooth_size: int):
        n = height * width
        self.shape = (height, width)
        self.history = History(MAX_SMOOTH_FRAMES)  # rendered colour and depth, this frame's in the spare slot
        self.smooth_size = smooth_size  # frames the smoothing history holds since it (re)started
        self.buffers = [_Buffers.empty(n), _Buffers.empty(n)]  # [this frame's, the previous frame's]
        self.previous: EyeCamera | None = None
        self.fov = Foveation.empty(n)
        self.fov_key: tuple | None = None
        self.central = 0
        self.color = np.empty((n, 3), np.float32)  # the presampled colour
        self.sub_mask = np.empty(n, np.uint8)
        self.first = np.empty(height + 1, np.int64)  # per row: the index of its first extra sample
        threads = nb.config.NUMBA_NUM_THREADS
        self.box = np.empty((threads, 6, width + 2))  # the inspection's 3x3 contrast boxes (_box_contrast_row)
        self.passes = np.empty((threads, width), np.bool_)
        self.extra_xy = np.empty((0, 2), np.float32)
        self.extra_keys = np.empty(0, np.int64)
        self.extra_color = np.empty((0, 3), np.float32)

    def extra(self, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """xy, keys and colour for `count` extra samples, grown by a quarter at least when too small."""
        if len(self.extra_keys) < count:
            size = max(count, len(self.extra_keys) * 5 // 4)
            self.extra_xy, self.extra_keys = np.empty((size, 2), np.float32), np.empty(size, np.int64)
            self.extra_color = np.empty((size, 3), np.float32)
        return self.extra_xy[:count], self.extra_keys[:count], self.extra_color[:count]


def _kept(buffers: _Buffers, history: History, slot: int) -> Kept:
    """A frame's Kept: its buffers, with the depth and colour of its history slot."""
    n = len(buffers.flags)
    depth, color = history.depth[slot].reshape(n), history.color[slot].reshape(n, 3)
    return Kept(buffers.ref, depth, buffers.flags, color, buffers.level, buffers.drift)


class _Frame(NamedTuple):
    """What the stages of one frame share: its request, the eye's state and foveation, this frame's and the
    previous frame's buffers, the history slot it is written to and both frames' kept colours, and its plan."""

    request: FrameRequest
    state: _EyeState
    fov: Foveation
    cur: _Buffers
    last: _Buffers
    slot: int
    kept: Kept
    prev: Kept
    steps: tuple[str, ...]

    @property
    def camera(self) -> EyeCamera:
        return self.request.camera


class Kim21(Configurable):
    """Selective foveated supersampling, reuse and smoothing on top of Whitted presampling."""

    name = "kim21"
    Params = Kim21Params
    # the samples per problematic subpixel down to 1 (section 4.6.2); the band edges move only with the foveal
    # widening (shrinking them changes tau_fov's shape, which may not hold)
    knobs = (
        *(Knob(f"n_{band}", 1) for band in ("f", "p", "m", "np")),
        *(Knob(f"e_{band}", None, foveal=True) for band in ("f", "p", "m", "np", "max")),
    )
    stages = (
        Stage("presample"),
        Stage("reuse", frozenset({HISTORY})),
        Stage("inspect"),
        Stage("supersample"),
        Stage("resolve"),
        Stage("smooth", frozenset({HISTORY})),
    )

    def __init__(self, tracer: Whitted, params: Kim21Params):
        self.tracer = tracer
        self._eyes: dict[str, _EyeState] = {}
        self._keys = np.empty(0, np.int64)
        self._keys_seed: int | None = None
        self._configure(params)

    @property
    def warmup_frames(self) -> int:
        """The earlier frames temporal smoothing blends (section 4.7), and one for pixel reuse (section 4.4); none
        for Jin et al.'s selective supersampling (neither)."""
        p = self.params
        return max(p.smooth_frames if p.smooth else 0, 1 if p.reuse else 0)

    def _configure(self, params: Kim21Params) -> None:
        """Keeps each eye's previous frame (pixel reuse goes on, its reuse counts included) and its
        smoothing history; new bands, sample counts and thresholds act on the next frame. Only a larger
        smooth_frames than an eye's history holds starts that history afresh (see render)."""
        p = params
        self.ctrl = bezier_controls(p)
        self.tests = Tests(
            np.array(
                [p.tau_col, p.tau_poid, p.tau_psn, p.tau_psc, p.tau_pte, p.tau_soid, p.tau_ssn, p.tau_ssc, p.tau_ste]
            ),
            p.normal_cos,
            p.tau_reuse,
            p.n_reuse_max,
            p.depth_tolerance,
            p.reuse_px,
        )
        self.bounds = np.array([p.e_f, p.e_p, p.e_m])
        self.counts = np.array([p.n_f, p.n_p, p.n_m, p.n_np], np.uint8)
        self.alpha = (alpha_knots(p), np.array(p.alpha))
        self.params = params

    def _state(self, eye: str, height: int, width: int) -> _EyeState:
        """The eye's buffers; a new image size starts them afresh, the smoothing history's size kept."""
        frames = max(self.params.smooth_frames, 1)
        state = self._eyes.get(eye)
        if state is None or state.shape != (height, width):
            state = self._eyes[eye] = _EyeState(height, width, frames if state is None else state.smooth_size)
        if state.smooth_size < frames:
            state.smooth_size = frames
            state.history.restart()
        return state

    def _foveation(self, state: _EyeState, cam: EyeCamera, gaze: np.ndarray) -> Foveation:
        """The eye's Foveation, recomputed when the frustum, the gaze or the parameters changed."""
        key = (cam.tan_left, cam.tan_right, cam.tan_up, cam.tan_down, float(gaze[0]), float(gaze[1]), float(gaze[2]))
        if state.fov_key is None or state.fov_key[0] != key or state.fov_key[1] is not self.params:
            ecc = eccentricity_map(cam, gaze)
            state.central = _foveation(
                ecc, self.ctrl, self.bounds, self.counts, self.params.e_np, *self.alpha, state.fov
            )
            state.fov_key = (key, self.params)
        return state.fov

    def _pixel_keys(self, n: int, seed: int) -> np.ndarray:
        """pixel_keys of pixels 0..n-1, kept while n and the seed stay."""
        if len(self._keys) != n or self._keys_seed != seed:
            self._keys, self._keys_seed = pixel_keys(np.arange(n), seed), seed
        return self._keys

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        f = self._frame(request, stats)
        color = self._presample(f, stats)
        reused = self._reuse(f, color, stats)
        problematic, extra_xy, extra_keys, extra_color = self._inspect_subpixels(f, stats)
        with stats.stage("supersample"):
            extra = self.tracer.trace_samples(f.camera, extra_xy, extra_keys, stats, out=extra_color)
        self._resolve_pixels(f, extra, stats)
        image = self._smooth(f, out, stats)
        f.state.history.commit(f.camera)
        f.state.previous = f.camera
        n = f.state.shape[0] * f.state.shape[1]
        stats.metrics["central_pixels"] = f.state.central
        stats.metrics["reused_pixels"] = reused
        stats.metrics["problematic_subpixels"] = problematic
        stats.metrics["extra_samples"] = len(extra)
        stats.metrics["sample_fraction"] = (n + len(extra)) / n
        return image

    def _frame(self, request: FrameRequest, stats: FrameStats) -> _Frame:
        """The eye's state and this frame's foveation, buffers (this frame's and the previous one's) and history
        slot, with the plan of its stages."""
        cam = request.camera
        h, w = cam.height, cam.width
        state = self._state(request.eye, h, w)
        steps = plan(self.stages, frozenset({HISTORY}) if state.previous is not None else frozenset())
        with stats.stage("eccentricity"):
            fov = self._foveation(state, cam, request.gaze)
        state.buffers.reverse()
        cur, last = state.buffers
        history = state.history
        slot, newest = history.begin((h, w)), max(history.newest((h, w)), 0)
        kept, prev = _kept(cur, history, slot), _kept(last, history, newest)
        return _Frame(request, state, fov, cur, last, slot, kept, prev, steps)

    def _presample(self, f: _Frame, stats: FrameStats) -> np.ndarray:
        """Section 4.3: one sample at every pixel centre, with the G-buffer (Table 1) the inspection reads."""
        h, w = f.state.shape
        with stats.stage("presample"):
            _clear(w, f.cur.gbuffer.secondary)
            keys = self._pixel_keys(h * w, f.request.seed)
            return self.tracer.trace_samples(f.camera, pixel_grid(w, h), keys, stats, f.cur.gbuffer, out=f.state.color)

    def _reuse(self, f: _Frame, color: np.ndarray, stats: FrameStats) -> int:
        """Section 4.4: each pixel's presample stored, its supersampled colour reused from the previous frame where
        the back-projection finds the same surface; returns how many pixels reused theirs."""
        cam, state = f.camera, f.state
        reuse = self.params.reuse and "reuse" in f.steps
        with stats.stage("reuse" if reuse else "store"):
            return dynamic(
                _store,
                state.shape[1],
                color,
                f.cur.gbuffer.primary,
                camera_arrays(cam).frustum,
                f.kept,
                relative_view(state.previous or cam, cam),
                f.last.gbuffer.primary,
                f.prev,
                same_camera(state.previous, cam),
                self.tests,
                reuse,
                f.fov.samples,
            )

    def _inspect_subpixels(self, f: _Frame, stats: FrameStats) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """Sections 3 and 4.6: the disparity test per subpixel, then the extra samples of the problematic ones
        (xy, keys and a colour buffer), after how many subpixels were problematic."""
        state, (h, w) = f.state, f.state.shape
        with stats.stage("inspect"):
            g1, g2 = f.cur.gbuffer
            scratch = (state.sub_mask, state.first, state.box, state.passes)
            problematic = _inspect(w, f.cur.ref, g1, g2, f.fov, f.cur.flags, self.tests, *scratch)
            state.first[h] = 0
            total = _exclusive_scan(state.first)
            extra_xy, extra_keys, extra_color = state.extra(total)
            seed_key = int(pixel_keys(np.zeros(1), f.request.seed, stream=1)[0])
            _subpixel_samples(w, state.sub_mask, f.fov.samples, state.first, seed_key, extra_xy, extra_keys)
        return problematic, extra_xy, extra_keys, extra_color

    def _resolve_pixels(self, f: _Frame, extra: np.ndarray, stats: FrameStats) -> None:
        """Section 4.6.2 and Figure 2: the rendered pixels' colours from their subpixels (_resolve)."""
        state, (h, w) = f.state, f.state.shape
        with stats.stage("resolve"):
            image, flags, interpolate = f.cur.ref.reshape(h, w, 3), f.cur.flags, self.params.interpolate
            dynamic(
                _resolve, image, state.sub_mask, f.fov.samples, flags, state.first, extra, interpolate, f.kept.rendered
            )

    def _smooth(self, f: _Frame, out: np.ndarray | None, stats: FrameStats) -> np.ndarray:
        """Section 4.7: exponential smoothing over the history by eccentricity; the frame as resolved without it."""
        p, history, (h, w) = self.params, f.state.history, f.state.shape
        image = np.empty((h, w, 3), np.float32) if out is None else out
        if not (p.smooth and p.smooth_frames and "smooth" in f.steps):
            image[:] = history.color[f.slot]
            return image
        alpha = f.fov.alpha.reshape(h, w)
        depth, color = history.depth[f.slot], history.color[f.slot]
        earlier = min(p.smooth_frames, len(history.order((h, w))))  # each read once, as the frame itself
        with stats.stage("smooth", touches=nbytes(alpha, image) + (1 + earlier) * nbytes(depth, color)):
            exponential_smoothing(f.camera, depth, color, alpha, history, p.smooth_frames, p.depth_tolerance, image)
        return image
