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
samples by band; the others take the colour interpolated from the four surrounding pixel centres.
Section 4.7: temporal smoothing over up to 4 back-projected earlier frames with alpha(e) piecewise
linear through 0.9, 0.8, 0.7, 0.5, 0.2, 0.1 at 0, e_f, e_p, e_m, e_np, e_max.

The paper leaves open when two normals disagree; here, when their dot product is below normal_cos.
The supersampling jitter is fixed per subpixel across frames: with a still view the frames agree,
and temporal smoothing works on what the paper targets, the noise of the received poses (Table 3).
"""

from __future__ import annotations

import math
from typing import Annotated

import msgspec
import numba as nb
import numpy as np

from hmdrt.errors import ConfigError
from hmdrt.foveation.base import HISTORY, Configurable, FrameRequest, Stage, pixel_keys, plan
from hmdrt.foveation.stages.reproject import bilinear3, camera_arrays, nearest_index, project, world_point
from hmdrt.foveation.stages.temporal import History, exponential_smoothing
from hmdrt.optics.camera import eccentricity_map, pixel_centres
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.gbuffer import GBuffer
from hmdrt.trace.integrator import Whitted
from hmdrt.trace.sampling import DIM_PIXEL, grid_dims, stratified

Positive = Annotated[float, msgspec.Meta(gt=0.0, le=1e3)]
Threshold = Annotated[float, msgspec.Meta(ge=0.0, le=10.0)]
Samples = Annotated[int, msgspec.Meta(ge=1, le=16)]
Deg = Annotated[float, msgspec.Meta(ge=0.0, le=180.0)]
Weight = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]  # a blending factor: above 1, (1 - a)^i changes sign
MAX_SUBPIXEL_SAMPLES = 16
POPCOUNT4 = np.array([bin(m).count("1") for m in range(16)], np.int64)


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
    # pixel reuse (section 4.4) and temporal smoothing (section 4.7)
    reuse: bool = True
    n_reuse_max: Annotated[int, msgspec.Meta(ge=0, le=1000)] = 5
    tau_reuse: Threshold = 1.0
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


@nb.njit(cache=True, nogil=True, inline="always")
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


@nb.njit(cache=True, nogil=True, inline="always")
def tau_fov(e, ctrl):
    """kim2021's tau_fov(e): y1(x1^-1(e)) on [0, e_f], y2(x2^-1(e)) on (e_f, e_np], tau_np beyond."""
    if e <= ctrl[2]:
        return _bezier_y_at_x(ctrl[0], ctrl[1], ctrl[2], ctrl[3], ctrl[4], ctrl[5], max(e, 0.0))
    if e <= ctrl[8]:
        return _bezier_y_at_x(ctrl[6], ctrl[7], ctrl[8], ctrl[9], ctrl[10], ctrl[11], e)
    return ctrl[11]


@nb.njit(cache=True, nogil=True)
def tau_fov_array(e, ctrl):
    out = np.empty(e.shape[0])
    for i in range(e.shape[0]):
        out[i] = tau_fov(e[i], ctrl)
    return out


def alpha_of_eccentricity(ecc: np.ndarray, p: Kim21Params) -> np.ndarray:
    """alpha(e), piecewise linear through p.alpha at (0, e_f, e_p, e_m, e_np, e_max), constant beyond."""
    return np.interp(ecc, (0.0, p.e_f, p.e_p, p.e_m, p.e_np, p.e_max), p.alpha).astype(np.float32)


MITCHELL = (1.36, 1.02, 2.04)  # kim2021 section 3: the contrast threshold vector per tau


@nb.njit(cache=True, nogil=True, inline="always")
def _contrast_fails(color, a, b, c, d, tau):
    """Mitchell's contrast (max - min) / (max + min) of rows a, b, c, d of color (n, 3), per channel,
    against tau x (1.36, 1.02, 2.04)."""
    for ch in range(3):
        va, vb, vc, vd = color[a, ch], color[b, ch], color[c, ch], color[d, ch]
        lo, hi = min(min(va, vb), min(vc, vd)), max(max(va, vb), max(vc, vd))
        if hi + lo > 0.0 and (hi - lo) / (hi + lo) > MITCHELL[ch] * tau:
            return True
    return False


@nb.njit(cache=True, nogil=True, inline="always")
def _pair_contrast_fails(color_a, i, color_b, j, tau):
    """Mitchell's contrast between pixel i of color_a and pixel j of color_b."""
    for ch in range(3):
        va, vb = color_a[i, ch], color_b[j, ch]
        lo, hi = min(va, vb), max(va, vb)
        if hi + lo > 0.0 and (hi - lo) / (hi + lo) > MITCHELL[ch] * tau:
            return True
    return False


@nb.njit(cache=True, nogil=True, inline="always")
def _discordant(i, j, obj, ns, shadow, tex, normal_cos):
    """Which of (object id, normal, shadow count, texture) differ between pixels i and j."""
    dot = ns[i, 0] * ns[j, 0] + ns[i, 1] * ns[j, 1] + ns[i, 2] * ns[j, 2]
    both_hit = obj[i] >= 0 and obj[j] >= 0
    return obj[i] != obj[j], both_hit and dot < normal_cos, shadow[i] != shadow[j], tex[i] != tex[j]


@nb.njit(cache=True, nogil=True, inline="always")
def _tau_sel(i, neighbours, p_attr, s_attr, thresholds, normal_cos):
    """Step one: the minimum threshold over geometry attributes on which pixel i disagrees with any
    neighbour; thresholds[0] (tau_col) when none does."""
    tau = thresholds[0]
    found = False
    for j in neighbours:
        d = _discordant(i, j, p_attr[0], p_attr[1], p_attr[2], p_attr[3], normal_cos)
        for k in range(4):
            if d[k]:
                tau = thresholds[1 + k] if not found else min(tau, thresholds[1 + k])
                found = True
        d = _discordant(i, j, s_attr[0], s_attr[1], s_attr[2], s_attr[3], normal_cos)
        for k in range(4):
            if d[k]:
                tau = thresholds[5 + k] if not found else min(tau, thresholds[5 + k])
                found = True
    return tau


@nb.njit(parallel=True, cache=True, nogil=True)
def _inspect(
    color,
    ecc,
    active,
    p_obj,
    p_ns,
    p_shadow,
    p_tex,
    s_obj,
    s_ns,
    s_shadow,
    s_tex,
    thresholds,
    ctrl,
    bounds,
    counts,
    normal_cos,
    width,
    sub_mask,
    samples,
):
    """The two-step disparity test of every subpixel of every active pixel: a 4-bit mask of the
    problematic subpixels (NW, NE, SW, SE) and the number of extra samples they take."""
    n = color.shape[0]
    height = n // width
    p_attr = (p_obj, p_ns, p_shadow, p_tex)
    s_attr = (s_obj, s_ns, s_shadow, s_tex)
    for i in nb.prange(n):
        sub_mask[i] = 0
        samples[i] = 0
        if not active[i]:
            continue
        x, y = i % width, i // width
        e = ecc[i]
        band = 0
        while band < 3 and e >= bounds[band]:
            band += 1
        tau_f = tau_fov(e, ctrl)
        for s in range(4):
            dx = -1 if s & 1 == 0 else 1
            dy = -1 if s < 2 else 1
            nx, ny = min(max(x + dx, 0), width - 1), min(max(y + dy, 0), height - 1)
            neighbours = (y * width + nx, ny * width + x, ny * width + nx)
            tau = _tau_sel(i, neighbours, p_attr, s_attr, thresholds, normal_cos) * tau_f
            if _contrast_fails(color, i, neighbours[0], neighbours[1], neighbours[2], tau):
                sub_mask[i] |= 1 << s
                samples[i] += counts[band]


@nb.njit(parallel=True, cache=True, nogil=True)
def _subpixel_samples(sub_mask, samples, first, counts_by_pixel, width, seed_key, xy, keys):
    """Stratified jittered positions of the extra samples, subpixel by subpixel (section 4.6.2)."""
    for i in nb.prange(sub_mask.shape[0]):
        m = sub_mask[i]
        if m == 0:
            continue
        x, y = i % width, i // width
        n = counts_by_pixel[i]
        nx, ny = grid_dims(n)
        j = first[i]
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


@nb.njit(parallel=True, cache=True, nogil=True)
def _resolve(color_ref, sub_mask, first, counts_by_pixel, extra, width, out):
    """Each pixel is the mean of its four subpixels: the mean of a problematic subpixel's samples, or
    the colour interpolated from the four surrounding pixel centres at the subpixel's centre."""
    n = sub_mask.shape[0]
    height = n // width
    image = color_ref.reshape(height, width, 3)
    for i in nb.prange(n):
        m = sub_mask[i]
        if m == 0:
            continue
        x, y = i % width, i // width
        k = counts_by_pixel[i]
        j = first[i]
        r = g = b = 0.0
        for s in range(4):
            if (m >> s) & 1:
                sr = sg = sb = 0.0
                for _ in range(k):
                    sr += extra[j, 0]
                    sg += extra[j, 1]
                    sb += extra[j, 2]
                    j += 1
                r, g, b = r + sr / k, g + sg / k, b + sb / k
            else:
                cr, cg, cb = bilinear3(image, x + 0.25 + 0.5 * (s & 1), y + 0.25 + 0.5 * (s >> 1))
                r, g, b = r + cr, g + cg, b + cb
        out[i, 0], out[i, 1], out[i, 2] = 0.25 * r, 0.25 * g, 0.25 * b


@nb.njit(parallel=True, cache=True, nogil=True)
def _reuse(
    cur_cam,
    prev_cam,
    depth,
    color_ref,
    central,
    p_obj,
    p_ns,
    p_shadow,
    p_tex,
    prev_depth,
    prev_ref,
    prev_obj,
    prev_ns,
    prev_shadow,
    prev_tex,
    prev_flags,
    prev_rendered,
    thresholds,
    tau_reuse,
    n_max,
    normal_cos,
    rel_depth,
    width,
    flags,
    rendered,
):
    """kim2021 section 4.4: flags[i] > 0 where pixel i reuses the previous frame's rendered colour."""
    n = depth.shape[0]
    height = n // width
    for i in nb.prange(n):
        flags[i] = 0
        if not central[i] or math.isinf(depth[i]) or p_obj[i] < 0:
            continue
        x, y = i % width, i // width
        px, py, pz = world_point(cur_cam, x + 0.5, y + 0.5, depth[i])
        qx, qy, dist = project(prev_cam, px, py, pz)
        j = nearest_index(qx, qy, width, height)
        if j < 0 or prev_flags[j] >= n_max or math.isinf(prev_depth[j]) or prev_obj[j] < 0:
            continue
        if abs(prev_depth[j] - dist) > rel_depth * dist:
            continue
        tau = thresholds[0]
        d = (
            p_obj[i] != prev_obj[j],
            p_ns[i, 0] * prev_ns[j, 0] + p_ns[i, 1] * prev_ns[j, 1] + p_ns[i, 2] * prev_ns[j, 2] < normal_cos,
            p_shadow[i] != prev_shadow[j],
            p_tex[i] != prev_tex[j],
        )
        found = False
        for k in range(4):
            if d[k]:
                tau = thresholds[1 + k] if not found else min(tau, thresholds[1 + k])
                found = True
        if _pair_contrast_fails(color_ref, i, prev_ref, j, tau * tau_reuse):
            continue
        flags[i] = prev_flags[j] + 1
        for c in range(3):
            rendered[i, c] = prev_rendered[j, c]


class _EyeState:
    """One eye's buffers carried to the next frame."""

    def __init__(self, history_size: int):
        self.history = History(history_size)
        self.gbuffers: list[GBuffer] = []
        self.previous: tuple | None = None  # camera, depth, colour ref, gbuffer, reuse flags, rendered colour


class Kim21(Configurable):
    """Selective foveated supersampling, reuse and smoothing on top of Whitted presampling."""

    name = "kim21"
    Params = Kim21Params
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
        self._configure(params)

    def _configure(self, params: Kim21Params) -> None:
        """Keeps each eye's previous frame (pixel reuse goes on, its reuse counts included) and its
        smoothing history; new bands, sample counts and thresholds act on the next frame. Only a larger
        smooth_frames than an eye's history holds starts that history afresh (see render)."""
        p = params
        self.ctrl = bezier_controls(p)
        self.thresholds = np.array(
            [p.tau_col, p.tau_poid, p.tau_psn, p.tau_psc, p.tau_pte, p.tau_soid, p.tau_ssn, p.tau_ssc, p.tau_ste]
        )
        self.bounds = np.array([p.e_f, p.e_p, p.e_m])
        self.counts = np.array([p.n_f, p.n_p, p.n_m, p.n_np], np.int64)
        self.params = params

    def _gbuffer(self, state: _EyeState, n: int) -> GBuffer:
        """A G-buffer for this frame that is not the previous frame's (two are kept and alternated)."""
        if not state.gbuffers or len(state.gbuffers[0].primary.depth) != n:
            state.gbuffers = [GBuffer.empty(n), GBuffer.empty(n)]
        state.gbuffers.reverse()
        state.gbuffers[0].secondary.clear()
        return state.gbuffers[0]

    def render(self, request: FrameRequest, stats: FrameStats) -> np.ndarray:
        cam, p = request.camera, self.params
        frames = max(p.smooth_frames, 1)
        state = self._eyes.setdefault(request.eye, _EyeState(frames))
        if state.history.size < frames:
            state.history = History(frames)
        history = (
            state.previous is not None
            and state.previous[0].width == cam.width
            and state.previous[0].height == cam.height
        )
        steps = plan(self.stages, frozenset({HISTORY}) if history else frozenset())
        n = cam.width * cam.height
        with stats.stage("eccentricity"):
            ecc = eccentricity_map(cam, request.gaze).reshape(-1)
            xy = pixel_centres(cam.width, cam.height)
        gbuf = self._gbuffer(state, n)
        with stats.stage("presample"):
            color_ref = self.tracer.trace_samples(cam, xy, pixel_keys(np.arange(n), request.seed), stats, gbuf)
        g1, g2 = gbuf.primary, gbuf.secondary
        central = ecc < p.e_np
        rendered = color_ref.copy()
        flags = np.zeros(n, np.int32)
        if p.reuse and "reuse" in steps:
            with stats.stage("reuse"):
                pcam, pdepth, pref, pg, pflags, prendered = state.previous
                pp = pg.primary
                _reuse(
                    camera_arrays(cam),
                    camera_arrays(pcam),
                    g1.depth,
                    color_ref,
                    central,
                    g1.object_id,
                    g1.normal_shading,
                    g1.shadow_count,
                    g1.textured,
                    pdepth,
                    pref,
                    pp.object_id,
                    pp.normal_shading,
                    pp.shadow_count,
                    pp.textured,
                    pflags,
                    prendered,
                    self.thresholds,
                    p.tau_reuse,
                    p.n_reuse_max,
                    p.normal_cos,
                    p.depth_tolerance,
                    cam.width,
                    flags,
                    rendered,
                )
        with stats.stage("inspect"):
            active = central & (flags == 0)
            sub_mask = np.empty(n, np.uint8)
            samples = np.empty(n, np.int64)
            _inspect(
                color_ref,
                ecc,
                active,
                g1.object_id,
                g1.normal_shading,
                g1.shadow_count,
                g1.textured,
                g2.object_id,
                g2.normal_shading,
                g2.shadow_count,
                g2.textured,
                self.thresholds,
                self.ctrl,
                self.bounds,
                self.counts,
                p.normal_cos,
                cam.width,
                sub_mask,
                samples,
            )
            first = np.cumsum(samples) - samples
            per_subpixel = np.where(samples > 0, samples // np.maximum(POPCOUNT4[sub_mask], 1), 0)
            extra_xy = np.empty((int(samples.sum()), 2), np.float32)
            extra_keys = np.empty(len(extra_xy), np.int64)
            _subpixel_samples(
                sub_mask,
                samples,
                first,
                per_subpixel,
                cam.width,
                int(pixel_keys(np.zeros(1), request.seed, stream=1)[0]),
                extra_xy,
                extra_keys,
            )
        with stats.stage("supersample"):
            extra = self.tracer.trace_samples(cam, extra_xy, extra_keys, stats) if len(extra_xy) else extra_xy
        with stats.stage("resolve"):
            _resolve(color_ref, sub_mask, first, per_subpixel, extra, cam.width, rendered)
        image = rendered.reshape(cam.height, cam.width, 3)
        depth = g1.depth.reshape(cam.height, cam.width)
        if p.smooth and p.smooth_frames and "smooth" in steps:
            with stats.stage("smooth"):
                alpha = alpha_of_eccentricity(ecc.reshape(cam.height, cam.width), p)
                image = exponential_smoothing(
                    cam, depth, image, alpha, state.history, p.smooth_frames, p.depth_tolerance
                )
        state.history.push(cam, depth, rendered.reshape(cam.height, cam.width, 3))
        state.previous = (cam, g1.depth, color_ref, gbuf, flags, rendered)
        stats.metrics["central_pixels"] = int(central.sum())
        stats.metrics["reused_pixels"] = int((flags > 0).sum())
        stats.metrics["problematic_subpixels"] = int(POPCOUNT4[sub_mask].sum())
        stats.metrics["extra_samples"] = len(extra_xy)
        stats.metrics["sample_fraction"] = (n + len(extra_xy)) / n
        return image
