"""Foveated real-time ray tracing with reprojection (weier2016).

Section 3.1: pixels are traced when xi_q < p(q), the foveal function of the foveal region
configuration (r0, r1, p_min); a low-resolution support image and support G-buffer (256 x 318 at
DK2's 1182 x 1464, scaled with the profile) are traced every frame. Section 3.2: the previous final
colour and cache info are reprojected through a coarse mesh built from the previous support G-buffer
(unprojected with the previous camera, projected with the current one), filtering each pixel's
footprint. Section 3.3: the resampling info marks support cells whose reprojected depth or luminance
jumps by more than eps_depth / eps_lum against a neighbour, or whose previous surface is seen at a
grazing angle (edge_t = max(n.d, 0) < eps_edge); their pixels are traced. Section 3.4: samples in the
fovea, in resampled cells, where nothing was reprojected, or whose depth disagrees with the cache by
more than eps_cache, replace the cache; the others update it with the running estimate (alpha, rho)
bounded below by k(dt) between k_min and k_max over t_max frames. Pixels left without colour are
merged from the support image. Section 3.5: when the scene has area lights or ambient occlusion, a
resampled pixel borrows the light buffer of the closest reconstructed pixel found by n random taps in
a window sized by the nearest reconstructed pixel along the image axes.

Values the paper leaves open (eps_*, k_min, k_max, t_max, footprint taps, post taps) are parameters
with defaults chosen here. Section 3.4 prints alpha = min(alpha', k); the running estimate uses
max(alpha', k), the lower bound the text describes (see stages.temporal.running_estimate).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import msgspec
import numba as nb
import numpy as np

from hmdrt.foveation.base import (
    HISTORY,
    STOCHASTIC,
    Configurable,
    FrameRequest,
    Stage,
    pixel_keys,
    plan,
    scene_features,
)
from hmdrt.foveation.stages.reproject import FAR, bilinear3, gather_previous, reproject_mesh
from hmdrt.foveation.stages.sampling import Foveal, bernoulli_mask, foveal_config
from hmdrt.foveation.stages.temporal import k_of_age, running_estimate
from hmdrt.optics.camera import EyeCamera, eccentricity_map
from hmdrt.rng import uniform
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.gbuffer import GBufferPool, LightBuffer
from hmdrt.trace.integrator import Whitted

Deg = Annotated[float, msgspec.Meta(ge=0.0, le=180.0)]
Fraction = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
DK2_SUPPORT = (256, 318, 1182, 1464)  # section 4.1: a 256 x 318 support image at 1182 x 1464
STATE = 6  # cache info per pixel: alpha, rho, frame last touched, and the light buffer's irradiance (rgb)


class Weier16Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    frc: Literal["small", "medium", "large", "full"] = "medium"
    r0: Deg | None = None
    r1: Deg | None = None
    p_min: Fraction | None = None
    support_w: Annotated[int, msgspec.Meta(ge=2, le=4096)] | None = None
    support_h: Annotated[int, msgspec.Meta(ge=2, le=4096)] | None = None
    eps_depth: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.05  # relative depth jump
    eps_lum: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.2  # luminance contrast |a - b| / (a + b)
    eps_edge: Fraction = 0.1  # grazing angle: edge_t = max(n.d, 0) below this
    eps_cache: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.05  # relative depth, cache vs new sample
    k_min: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.1
    k_max: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 1.0
    t_max: Annotated[float, msgspec.Meta(ge=1.0, le=1e6)] = 15.0
    footprint_samples: Annotated[int, msgspec.Meta(ge=1, le=64)] = 4
    post: bool = True
    post_samples: Annotated[int, msgspec.Meta(ge=1, le=256)] = 8
    post_radius: Annotated[int, msgspec.Meta(ge=1, le=1024)] = 32  # pixels searched along each axis

    def __post_init__(self) -> None:
        if self.k_min > self.k_max:
            raise ValueError("k_min must not exceed k_max")

    def foveal(self) -> Foveal:
        return foveal_config(self.frc, self.r0, self.r1, self.p_min)


def support_size(params: Weier16Params, width: int, height: int) -> tuple[int, int]:
    """The support image's size: as given, else 256 x 318 scaled from DK2's resolution to this one."""
    sw, sh, dw, dh = DK2_SUPPORT
    w = params.support_w or max(2, round(width * sw / dw))
    h = params.support_h or max(2, round(height * sh / dh))
    return min(w, width), min(h, height)


def support_grid(width: int, height: int, sw: int, sh: int) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution pixel coordinates of the support pixels' centres."""
    return (np.arange(sw) + 0.5) * width / sw, (np.arange(sh) + 0.5) * height / sh


@nb.njit(parallel=True, cache=True, nogil=True)
def _resampling_info(
    mesh, zinv, prev_color, prev_normal, prev_cam_pos, full_w, full_h, eps_depth, eps_lum, eps_edge, out
):
    """weier2016 section 3.3 at support resolution: depth or luminance discontinuities between a cell
    and its 4-neighbours in the reprojected support image, grazing surfaces, and uncovered cells."""
    h, w = zinv.shape
    ph, pw = prev_color.shape[0], prev_color.shape[1]
    depth = np.empty((h, w))
    lum = np.empty((h, w))
    for y in nb.prange(h):
        for x in range(w):
            if zinv[y, x] <= 0.0:
                depth[y, x] = math.nan
                continue
            depth[y, x] = 1.0 / zinv[y, x]
            sx, sy = mesh[y, x, 0] * pw / full_w, mesh[y, x, 1] * ph / full_h  # previous support coordinates
            r, g, b = bilinear3(prev_color, sx, sy)
            lum[y, x] = 0.2126 * r + 0.7152 * g + 0.0722 * b
    for y in nb.prange(h):
        for x in range(w):
            d = depth[y, x]
            if math.isnan(d):
                out[y, x] = True
                continue
            mark = False
            for dy, dx in ((0, 1), (1, 0), (0, -1), (-1, 0)):
                ny, nx = y + dy, x + dx
                if ny < 0 or nx < 0 or ny >= h or nx >= w or math.isnan(depth[ny, nx]):
                    continue
                dn = depth[ny, nx]
                if abs(dn - d) > eps_depth * min(dn, d):
                    mark = True
                la, lb = lum[y, x], lum[ny, nx]
                if la + lb > 0.0 and abs(la - lb) / (la + lb) > eps_lum:
                    mark = True
            if not mark:
                # grazing test with the previous frame's geometric normal and the direction to its eye
                sx = min(max(int(mesh[y, x, 0] * pw / full_w), 0), pw - 1)
                sy = min(max(int(mesh[y, x, 1] * ph / full_h), 0), ph - 1)
                nx_, ny_, nz_ = prev_normal[sy, sx, 0], prev_normal[sy, sx, 1], prev_normal[sy, sx, 2]
                if nx_ != 0.0 or ny_ != 0.0 or nz_ != 0.0:
                    vx = prev_cam_pos[0] - mesh[y, x, 2]
                    vy = prev_cam_pos[1] - mesh[y, x, 3]
                    vz = prev_cam_pos[2] - mesh[y, x, 4]
                    inv = 1.0 / max(math.sqrt(vx * vx + vy * vy + vz * vz), 1e-30)
                    mark = max((nx_ * vx + ny_ * vy + nz_ * vz) * inv, 0.0) < eps_edge
            out[y, x] = mark


@nb.njit(parallel=True, cache=True, nogil=True)
def _cache_update(
    pixels,
    sample_rgb,
    sample_depth,
    sample_light,
    fresh,
    covered,
    re_color,
    re_state,
    re_dist,
    frame,
    k_min,
    k_max,
    t_max,
    eps_cache,
    out_color,
    out_state,
    has_color,
):
    """weier2016 section 3.4 for every traced pixel; reprojected pixels that were not traced keep their cache."""
    h, w = covered.shape
    for y in nb.prange(h):
        for x in range(w):
            has_color[y, x] = covered[y, x]
            if covered[y, x]:
                for c in range(3):
                    out_color[y, x, c] = re_color[y, x, c]
                for c in range(STATE):
                    out_state[y, x, c] = re_state[y, x, c]
    for s in nb.prange(pixels.shape[0]):
        i = pixels[s]
        y, x = i // w, i % w
        d = sample_depth[s]
        new = fresh[s] or not covered[y, x]
        if not new:
            far_sample, far_cache = d >= FAR or math.isinf(d), re_dist[y, x] >= 0.5 * FAR
            if far_sample != far_cache or (not far_sample and abs(re_dist[y, x] - d) > eps_cache * d):
                new = True
        if new:
            alpha, rho = 1.0, 1.0
        else:
            k = k_of_age(frame - re_state[y, x, 2], k_min, k_max, t_max)
            alpha, rho = running_estimate(max(re_state[y, x, 1], 1.0), k)
        for c in range(3):
            out_color[y, x, c] = alpha * sample_rgb[s, c] + (1.0 - alpha) * (0.0 if new else re_color[y, x, c])
            prev_e = 0.0 if new else re_state[y, x, 3 + c]
            out_state[y, x, 3 + c] = alpha * sample_light[s, c] + (1.0 - alpha) * prev_e
        out_state[y, x, 0], out_state[y, x, 1], out_state[y, x, 2] = alpha, rho, frame
        has_color[y, x] = True


@nb.njit(parallel=True, cache=True, nogil=True)
def _merge(support, has_color, color):
    """Pixels without colour take the bilinearly upsampled support image."""
    h, w = has_color.shape
    sh, sw = support.shape[0], support.shape[1]
    for y in nb.prange(h):
        for x in range(w):
            if not has_color[y, x]:
                r, g, b = bilinear3(support, (x + 0.5) * sw / w, (y + 0.5) * sh / h)
                color[y, x, 0], color[y, x, 1], color[y, x, 2] = r, g, b


@nb.njit(parallel=True, cache=True, nogil=True)
def _post(pixels, resampled, sample_light, sample_albedo, reconstructed, state, radius, taps, seed, color):
    """weier2016 section 3.5: a resampled pixel borrows the accumulated light buffer of the closest
    reconstructed pixel among `taps` random taps in a window sized by the nearest reconstructed pixel
    along the image axes."""
    h, w = reconstructed.shape
    for s in nb.prange(pixels.shape[0]):
        if not resampled[s]:
            continue
        i = pixels[s]
        y, x = i // w, i % w
        reach = 0
        for dist in range(1, radius + 1):
            if (
                (x + dist < w and reconstructed[y, x + dist])
                or (x - dist >= 0 and reconstructed[y, x - dist])
                or (y + dist < h and reconstructed[y + dist, x])
                or (y - dist >= 0 and reconstructed[y - dist, x])
            ):
                reach = dist
                break
        if reach == 0:
            continue
        best, best_d2 = -1, 1e30
        for t in range(taps):
            ox = int(math.floor((2.0 * uniform(i + seed, 11, 2 * t) - 1.0) * reach + 0.5))
            oy = int(math.floor((2.0 * uniform(i + seed, 11, 2 * t + 1) - 1.0) * reach + 0.5))
            ty, tx = y + oy, x + ox
            if 0 <= ty < h and 0 <= tx < w and reconstructed[ty, tx] and ox * ox + oy * oy < best_d2:
                best, best_d2 = ty * w + tx, ox * ox + oy * oy
        if best < 0:
            continue
        by, bx = best // w, best % w
        for c in range(3):
            # colour minus its own stochastic part is >= 0 exactly; max() only absorbs float rounding
            rest = max(color[y, x, c] - sample_albedo[s, c] * sample_light[s, c], 0.0)
            color[y, x, c] = rest + sample_albedo[s, c] * state[by, bx, 3 + c]


@dataclass
class _EyeState:
    camera: EyeCamera
    color: np.ndarray  # (h, w, 3) final colour
    state: np.ndarray  # (h, w, STATE) cache info
    support_depth: np.ndarray  # (sh, sw)
    support_normal: np.ndarray  # (sh, sw, 3) geometric normal
    support_color: np.ndarray  # (sh, sw, 3)


class Weier16(Configurable):
    """Foveated ray tracing with coarse-mesh reprojection, resampling info, cache and merge."""

    name = "weier16"
    Params = Weier16Params
    stages = (
        Stage("sample"),
        Stage("reproject", frozenset({HISTORY})),
        Stage("resample_info", frozenset({HISTORY})),
        Stage("trace"),
        Stage("cache_update"),
        Stage("merge"),
        Stage("post", frozenset({HISTORY, STOCHASTIC})),
    )

    def __init__(self, tracer: Whitted, params: Weier16Params):
        self.tracer = tracer
        self.features = scene_features(tracer)
        self._eyes: dict[str, _EyeState] = {}
        self._gbuffers = GBufferPool()
        self._configure(params)

    def _configure(self, params: Weier16Params) -> None:
        """Keeps each eye's final colour, cache info and support G-buffer: a new foveal region (frc, r0,
        r1, p_min) or new thresholds act on the next frame's samples and cache update, which reprojects
        the cache as usual. A new support size (support_w, support_h) cannot use the previous support
        G-buffer as its coarse mesh, so the next frame starts without history."""
        foveal = params.foveal()
        self.params, self.foveal = params, foveal

    def render(self, request: FrameRequest, stats: FrameStats) -> np.ndarray:
        cam, p, t = request.camera, self.params, request.frame
        w, h = cam.width, cam.height
        sw, sh = support_size(p, w, h)
        prev = self._eyes.get(request.eye)
        history = prev is not None and prev.color.shape[:2] == (h, w) and prev.support_depth.shape == (sh, sw)
        steps = plan(self.stages, self.features | ({HISTORY} if history else set()))
        gx, gy = support_grid(w, h, sw, sh)
        with stats.stage("sample"):
            ecc = eccentricity_map(cam, request.gaze)
            mask = bernoulli_mask(ecc, self.foveal, request.seed, t)
            fovea = ecc < self.foveal.r0
        covered = np.zeros((h, w), bool)
        re_color = re_state = re_dist = None
        if "reproject" in steps:
            with stats.stage("reproject"):
                mesh, zinv = reproject_mesh(prev.camera, gx, gy, prev.support_depth, cam, w, h)
                re_color, re_state, re_dist = gather_previous(
                    mesh, zinv, cam, prev.color, prev.state, p.footprint_samples, request.seed + t
                )
                covered = zinv > 0
        resample = np.zeros((h, w), bool)
        if "resample_info" in steps:
            with stats.stage("resample_info"):
                low_mesh, low_zinv = reproject_mesh(prev.camera, gx, gy, prev.support_depth, cam, sw, sh)
                low = np.empty((sh, sw), bool)
                _resampling_info(
                    low_mesh,
                    low_zinv,
                    prev.support_color,
                    prev.support_normal,
                    prev.camera.position,
                    float(w),
                    float(h),
                    p.eps_depth,
                    p.eps_lum,
                    p.eps_edge,
                    low,
                )
                resample = low[(np.arange(h) * sh // h)[:, None], (np.arange(w) * sw // w)[None, :]]
        with stats.stage("trace"):
            traced = mask | resample
            pixels = np.flatnonzero(traced)
            xy = np.empty((len(pixels) + sw * sh, 2), np.float32)
            xy[: len(pixels), 0] = pixels % w + 0.5
            xy[: len(pixels), 1] = pixels // w + 0.5
            xy[len(pixels) :, 0] = np.tile(gx, sh)
            xy[len(pixels) :, 1] = np.repeat(gy, sw)
            keys = np.concatenate(
                [pixel_keys(pixels, request.seed, t), pixel_keys(np.arange(sw * sh), request.seed, t, 2)]
            )
            gbuf = self._gbuffers.rows(len(xy))
            light = LightBuffer.empty(len(xy)) if STOCHASTIC in self.features else None
            rgb = self.tracer.trace_samples(cam, xy, keys, stats, gbuf, light)
        n = len(pixels)
        with stats.stage("cache_update"):
            color = np.zeros((h, w, 3), np.float32)
            state = np.zeros((h, w, STATE), np.float32)
            has_color = np.empty((h, w), bool)
            fresh = (fovea | resample).reshape(-1)[pixels]
            if re_color is None:
                re_color, re_state, re_dist = color, state, np.full((h, w), np.nan, np.float32)
            sample_light = light.irradiance[:n] if light is not None else np.zeros((n, 3), np.float32)
            _cache_update(
                pixels,
                rgb[:n],
                gbuf.primary.depth[:n],
                sample_light,
                fresh,
                covered,
                re_color,
                re_state,
                re_dist,
                float(t),
                p.k_min,
                p.k_max,
                p.t_max,
                p.eps_cache,
                color,
                state,
                has_color,
            )
        support_color = rgb[n:].reshape(sh, sw, 3)
        with stats.stage("merge"):
            _merge(support_color, has_color, color)
        if p.post and "post" in steps and light is not None:
            with stats.stage("post"):
                reconstructed = has_color & ~resample & covered
                _post(
                    pixels,
                    resample.reshape(-1)[pixels],
                    light.irradiance[:n],
                    light.albedo[:n],
                    reconstructed,
                    state,
                    p.post_radius,
                    p.post_samples,
                    request.seed + t,
                    color,
                )
        self._eyes[request.eye] = _EyeState(
            cam,
            color,
            state,
            gbuf.primary.depth[n:].reshape(sh, sw).copy(),
            gbuf.primary.normal_geometric[n:].reshape(sh, sw, 3).copy(),
            support_color,
        )
        stats.metrics["sample_fraction"] = n / (w * h)
        stats.metrics["resampled_pixels"] = int(resample.sum())
        stats.metrics["support_rays"] = sw * sh
        stats.metrics["merged_pixels"] = int((~has_color).sum())
        return color
