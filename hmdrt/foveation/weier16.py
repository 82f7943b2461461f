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

Each frame reprojects the mesh, marks the resampling info, selects and traces the samples, then runs
one pass that gathers the previous frame through the mesh, applies the running estimate and merges,
reading one of two persistent final buffers per eye and writing the other and the caller's image;
nothing of the image's size is allocated per frame.

Values the paper leaves open (eps_*, k_min, k_max, t_max, footprint taps, post taps) are parameters
with defaults chosen here. Section 3.4 prints alpha = min(alpha', k); the running estimate uses
max(alpha', k), the lower bound the text describes (see stages.temporal.running_estimate).
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal, NamedTuple

import msgspec
import numba as nb
import numpy as np

from hmdrt.foveation.base import (
    HISTORY,
    STOCHASTIC,
    Configurable,
    FrameRequest,
    Stage,
    plan,
    scene_features,
)
from hmdrt.foveation.stages.reproject import (
    ROWS,
    CoarseMesh,
    MeshImage,
    dynamic,
    gaussian_taps,
    nearest_texel,
    row_footprints,
)
from hmdrt.foveation.stages.sampling import FOVEAL_REGION_KNOBS, Foveal, foveal_config, foveal_probability
from hmdrt.foveation.stages.temporal import k_of_age, running_estimate
from hmdrt.jit import inline, kernel, serial
from hmdrt.optics.camera import EyeCamera, eccentricity_map
from hmdrt.optics.projection import FAR, bilinear3, camera_arrays, view_distance, view_point
from hmdrt.ranges import Deg, Fraction
from hmdrt.rng import uniform
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.gbuffer import GBufferPool, LightBuffer
from hmdrt.trace.integrator import Whitted

DK2_SUPPORT = (256, 318, 1182, 1464)  # section 4.1: a 256 x 318 support image at 1182 x 1464
INFO = 3  # cache info per pixel: alpha, rho and the frame it was last touched
TRACED, FRESH, RESAMPLE, COVERED = 1, 2, 4, 8  # a pixel's flags: traced this frame; its sample replaces the
# cache (fovea or resampled); marked in the resampling info; covered by the reprojected mesh
SUPPORT_STREAM = 2 << 40  # base.pixel_keys stream 2: the support image's samples


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


class Support(NamedTuple):
    """A frame's support image and support G-buffer (section 3.1), the next frame's coarse mesh."""

    depth: np.ndarray  # (sh, sw) float32 hit distance
    normal: np.ndarray  # (sh, sw, 3) float32 geometric normal
    color: np.ndarray  # (sh, sw, 3) float32

    @classmethod
    def empty(cls, sw: int, sh: int) -> Support:
        return cls(np.empty((sh, sw), np.float32), np.empty((sh, sw, 3), np.float32), np.empty((sh, sw, 3), np.float32))


class Final(NamedTuple):
    """A frame's final colour and cache info (section 3.4) and its accumulated light buffer (section 3.5),
    which stays zero in a scene without stochastic lights."""

    color: np.ndarray  # (h, w, 3) float32
    info: np.ndarray  # (h, w, INFO) float32
    light: np.ndarray  # (h, w, 3) float32 irradiance

    @classmethod
    def empty(cls, w: int, h: int) -> Final:
        return cls(np.empty((h, w, 3), np.float32), np.empty((h, w, INFO), np.float32), np.zeros((h, w, 3), np.float32))


class Selection(NamedTuple):
    """Where the frame traces: per pixel its flags, per row its samples (they are in scanline order)."""

    flags: np.ndarray  # (h, w) uint8: TRACED, FRESH, RESAMPLE, COVERED
    counts: np.ndarray  # (h,) int64 traced pixels per row
    row_start: np.ndarray  # (h + 1,) int64: the first sample of each row
    resampled: np.ndarray  # (h,) int64 pixels per row marked in the resampling info
    merged: np.ndarray  # (h,) int64 pixels per row taken from the support image


class Samples(NamedTuple):
    """The frame's traced samples, pixels in scanline order, then the support image's."""

    rgb: np.ndarray  # (n + support, 3) float32
    depth: np.ndarray  # (n + support,) float32 primary hit distance
    light: np.ndarray  # (n + support, 3) float32 light buffer irradiance; zero without stochastic lights
    albedo: np.ndarray  # (n + support, 3) float32 light buffer albedo


class Thresholds(NamedTuple):
    """Section 3.3's resampling thresholds."""

    depth: float
    lum: float
    edge: float


class CacheRule(NamedTuple):
    """Section 3.4's running estimate and section 3.2's footprint filter for one frame."""

    frame: float
    k_min: float
    k_max: float
    t_max: float
    eps_cache: float
    footprint_samples: int
    seed: int  # of the footprint's taps
    stochastic: bool  # the light buffer is accumulated too


class _Buffers:
    """Everything a frame of one size works in, shared by the eyes (they render one after the other), kept
    across frames: the two coarse meshes, the resampling info, the selection, the sample list given to the
    tracer and the geometry of the support grid. Replaced when the image or the support size changes."""

    def __init__(self, w: int, h: int, sw: int, sh: int):
        self.size = (w, h, sw, sh)
        self.mesh = CoarseMesh()  # at full resolution
        self.low_mesh = CoarseMesh()  # at support resolution, for the resampling info
        self.resample = np.empty((sh, sw), bool)
        self.low_scratch = np.empty((2, sh, sw))  # reprojected depth and luminance
        self.no_resample = np.zeros((0, 0), bool)  # stand-ins for a frame without history
        self.no_zinv = np.zeros((0, 0), np.float32)
        self.selection = Selection(
            np.empty((h, w), np.uint8),
            np.empty(h, np.int64),
            np.zeros(h + 1, np.int64),
            np.empty(h, np.int64),
            np.empty(h, np.int64),
        )
        self.grid_x, self.grid_y = (np.arange(sw) + 0.5) * w / sw, (np.arange(sh) + 0.5) * h / sh
        self.low_cols = np.arange(w) * sw // w  # the support column each pixel's resampling info comes from
        self.footprints = np.empty((nb.config.NUMBA_NUM_THREADS, w), np.float32)  # a row's, per thread
        # the sample list for the most a frame can trace, every pixel and the support image: pages a frame
        # never reaches are never touched, so this costs memory only as far as frames fill it
        most = w * h + sw * sh
        self.xy, self.keys = np.empty((most, 2), np.float32), np.empty(most, np.int64)
        self.light = LightBuffer.empty(most)  # zeros: without stochastic lights the tracer leaves it so

    def sample_list(self, n: int) -> tuple[np.ndarray, np.ndarray, LightBuffer]:
        """xy, keys and light buffer rows for n samples."""
        return self.xy[:n], self.keys[:n], LightBuffer(self.light.irradiance[:n], self.light.albedo[:n])


@kernel
def _resampling_info(mesh, cur, support, prev_position, full_w, full_h, eps, scratch, out):
    """weier2016 section 3.3 at support resolution: depth or luminance discontinuities between a cell
    and its 4-neighbours in the reprojected support image, grazing surfaces, and uncovered cells."""
    prev, zinv = mesh.prev, mesh.zinv
    prev_color, prev_normal = support.color, support.normal
    depth, lum = scratch[0], scratch[1]
    h, w = zinv.shape
    ph, pw = prev_color.shape[0], prev_color.shape[1]
    for y in nb.prange(h):
        for x in range(w):
            if zinv[y, x] <= 0.0:
                depth[y, x] = math.nan
                continue
            depth[y, x] = 1.0 / zinv[y, x]
            sx, sy = prev[0, y, x] * pw / full_w, prev[1, y, x] * ph / full_h  # previous support coordinates
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
                if abs(dn - d) > eps.depth * min(dn, d):
                    mark = True
                la, lb = lum[y, x], lum[ny, nx]
                if la + lb > 0.0 and abs(la - lb) / (la + lb) > eps.lum:
                    mark = True
            if not mark:
                # grazing test with the previous frame's geometric normal and the direction to its eye
                sx = min(max(int(prev[0, y, x] * pw / full_w), 0), pw - 1)
                sy = min(max(int(prev[1, y, x] * ph / full_h), 0), ph - 1)
                nx_, ny_, nz_ = prev_normal[sy, sx, 0], prev_normal[sy, sx, 1], prev_normal[sy, sx, 2]
                if nx_ != 0.0 or ny_ != 0.0 or nz_ != 0.0:
                    px, py, pz = view_point(cur, x + 0.5, y + 0.5, d)
                    vx, vy, vz = prev_position[0] - px, prev_position[1] - py, prev_position[2] - pz
                    inv = 1.0 / max(math.sqrt(vx * vx + vy * vy + vz * vz), 1e-30)
                    mark = max((nx_ * vx + ny_ * vy + nz_ * vz) * inv, 0.0) < eps.edge
            out[y, x] = mark


@kernel
def _select(ecc, foveal, seed, frame, zinv, resample, low_cols, selection):
    """Section 3.1's ray generation (pixel q traced when xi_q < p(q), sampling.bernoulli_mask's xi) and the
    pixels of cells marked in the resampling info, with each pixel's flags and each row's sample count."""
    flags, counts, resampled = selection.flags, selection.counts, selection.resampled
    h, w = flags.shape
    sh = resample.shape[0]
    history = zinv.shape[0] == h
    for y in nb.prange(h):
        ly = y * sh // h
        n = nr = 0
        for x in range(w):
            e = ecc[y, x]
            f = COVERED if history and zinv[y, x] > 0.0 else 0
            if sh > 0 and resample[ly, low_cols[x]]:
                f |= TRACED | FRESH | RESAMPLE
                nr += 1
            elif e < foveal.r0:  # p(q) = 1
                f |= TRACED | FRESH
            else:
                p = foveal_probability(e, foveal.r0, foveal.r1, foveal.p_min)
                if p >= 1.0 or uniform(y * w + x + (seed << 32), 0x5A3, frame) < p:
                    f |= TRACED
            flags[y, x] = f
            n += f & TRACED
        counts[y] = n
        resampled[y] = nr


@kernel
def _fill_samples(flags, row_start, grid_x, grid_y, key_base, xy, keys):
    """Pixel centres and random-stream keys of the traced pixels in scanline order, then of the support grid
    (base.pixel_keys: stream 0 for pixels, 2 for the support image)."""
    h, w = flags.shape
    for y in nb.prange(h):
        s = row_start[y]
        for x in range(w):
            if flags[y, x] & TRACED:
                xy[s, 0], xy[s, 1] = x + 0.5, y + 0.5
                keys[s] = y * w + x + key_base
                s += 1
    n, sw = row_start[h], grid_x.shape[0]
    for j in nb.prange(grid_y.shape[0]):
        for i in range(sw):
            k = n + j * sw + i
            xy[k, 0], xy[k, 1] = grid_x[i], grid_y[j]
            keys[k] = j * sw + i + key_base + SUPPORT_STREAM


@inline
def _moved(depth, dist, eps_cache):
    """Section 3.4: the sample's surface is not the cached one: one of them a miss and the other not, or
    their distances from the eye apart by more than eps_cache of the sample's."""
    far_sample, far_cache = depth >= FAR or math.isinf(depth), dist >= 0.5 * FAR
    return far_sample != far_cache or (not far_sample and abs(dist - depth) > eps_cache * depth)


@serial
def _update_rows(y0, y1, selection, mesh, cur, previous, samples, support, rule, scratch, final, image):
    flags, row_start = selection.flags, selection.row_start
    prev, zinv = mesh.prev, mesh.zinv
    prev_color, prev_info, prev_light = previous.color, previous.info, previous.light
    rgb, sample_depth, sample_light = samples.rgb, samples.depth, samples.light
    color, info, light = final.color, final.info, final.light
    h, w = flags.shape
    sh, sw = support.shape[0], support.shape[1]
    spread_row = scratch[nb.get_thread_id()]
    history = zinv.shape[0] == h  # else no pixel is covered, and the mesh buffers may be empty
    for y in range(y0, y1):
        if history:
            row_footprints(prev, flags, COVERED, y, spread_row)
        s = row_start[y]
        merged = 0
        for x in range(w):
            f = flags[y, x]
            covered, traced = (f & COVERED) != 0, (f & TRACED) != 0
            new = traced and (
                (f & FRESH) != 0
                or not covered
                or _moved(
                    sample_depth[s], np.float32(view_distance(cur, x + 0.5, y + 0.5, 1.0 / zinv[y, x])), rule.eps_cache
                )
            )
            r = g = b = 0.0
            jy = jx = 0
            if covered and not new:  # the previous frame seen through the mesh
                qx, qy, spread = prev[0, y, x], prev[1, y, x], spread_row[x]
                if spread <= 1.5 or rule.footprint_samples <= 1:
                    r, g, b = bilinear3(prev_color, qx, qy)
                else:
                    key = (y * w + x) * 64 + rule.seed
                    r, g, b = gaussian_taps(prev_color, qx, qy, 0.5 * spread, rule.footprint_samples, key)
                r, g, b = np.float32(r), np.float32(g), np.float32(b)  # the reprojected image is float32
                jy, jx = nearest_texel(qx, qy, w, h)  # cache info is not blended: the nearest texel
            if traced:
                alpha, rho = 1.0, 1.0
                if not new:
                    k = k_of_age(rule.frame - prev_info[jy, jx, 2], rule.k_min, rule.k_max, rule.t_max)
                    alpha, rho = running_estimate(max(prev_info[jy, jx, 1], 1.0), k)
                color[y, x, 0] = alpha * rgb[s, 0] + (1.0 - alpha) * r
                color[y, x, 1] = alpha * rgb[s, 1] + (1.0 - alpha) * g
                color[y, x, 2] = alpha * rgb[s, 2] + (1.0 - alpha) * b
                info[y, x, 0], info[y, x, 1], info[y, x, 2] = alpha, rho, rule.frame
                if rule.stochastic:
                    for c in range(3):
                        kept = 0.0 if new else prev_light[jy, jx, c]
                        light[y, x, c] = alpha * sample_light[s, c] + (1.0 - alpha) * kept
                s += 1
            elif covered:
                color[y, x, 0], color[y, x, 1], color[y, x, 2] = r, g, b
                for c in range(INFO):
                    info[y, x, c] = prev_info[jy, jx, c]
                if rule.stochastic:
                    for c in range(3):
                        light[y, x, c] = prev_light[jy, jx, c]
            else:  # the merge: the bilinearly upsampled support image
                r, g, b = bilinear3(support, (x + 0.5) * sw / w, (y + 0.5) * sh / h)
                color[y, x, 0], color[y, x, 1], color[y, x, 2] = r, g, b
                for c in range(INFO):
                    info[y, x, c] = 0.0
                if rule.stochastic:
                    for c in range(3):
                        light[y, x, c] = 0.0
                merged += 1
            for c in range(3):
                image[y, x, c] = color[y, x, c]
        selection.merged[y] = merged


@kernel
def _update(selection, mesh, cur, previous, samples, support, rule, scratch, final, image):
    """Sections 3.2 and 3.4 in one pass: each pixel's previous colour and cache info gathered through the
    mesh, its sample merged into them with the running estimate (or replacing them: fovea, resampled,
    uncovered or moved), and pixels left without colour taken from the support image; into the final
    colour, cache info and the caller's image."""
    h = selection.flags.shape[0]
    for b in nb.prange((h + ROWS - 1) // ROWS):
        _update_rows(
            b * ROWS,
            min(h, (b + 1) * ROWS),
            selection,
            mesh,
            cur,
            previous,
            samples,
            support,
            rule,
            scratch,
            final,
            image,
        )


@inline
def _reconstructed(flags):
    """Covered by the reprojection and not resampled: a pixel whose cache the post filter may borrow."""
    return flags & (COVERED | RESAMPLE) == COVERED


@serial
def _post_rows(y0, y1, selection, samples, light, radius, taps, seed, color, image):
    for y in range(y0, y1):
        if selection.resampled[y]:
            _post_row(y, selection, samples, light, radius, taps, seed, color, image)


@inline
def _post_row(y, selection, samples, light, radius, taps, seed, color, image):
    flags = selection.flags
    h, w = flags.shape
    s = selection.row_start[y] - 1
    for x in range(w):
        if not flags[y, x] & TRACED:
            continue
        s += 1
        if not flags[y, x] & RESAMPLE:
            continue
        reach = 0
        for dist in range(1, radius + 1):
            if (
                (x + dist < w and _reconstructed(flags[y, x + dist]))
                or (x - dist >= 0 and _reconstructed(flags[y, x - dist]))
                or (y + dist < h and _reconstructed(flags[y + dist, x]))
                or (y - dist >= 0 and _reconstructed(flags[y - dist, x]))
            ):
                reach = dist
                break
        if reach == 0:
            continue
        i = y * w + x
        best, best_d2 = -1, 1e30
        for t in range(taps):
            ox = int(math.floor((2.0 * uniform(i + seed, 11, 2 * t) - 1.0) * reach + 0.5))
            oy = int(math.floor((2.0 * uniform(i + seed, 11, 2 * t + 1) - 1.0) * reach + 0.5))
            ty, tx = y + oy, x + ox
            if 0 <= ty < h and 0 <= tx < w and _reconstructed(flags[ty, tx]) and ox * ox + oy * oy < best_d2:
                best, best_d2 = ty * w + tx, ox * ox + oy * oy
        if best < 0:
            continue
        by, bx = best // w, best % w
        for c in range(3):
            # colour minus its own stochastic part is >= 0 exactly; max() only absorbs float rounding
            rest = max(color[y, x, c] - samples.albedo[s, c] * samples.light[s, c], 0.0)
            color[y, x, c] = rest + samples.albedo[s, c] * light[by, bx, c]
            image[y, x, c] = color[y, x, c]


@kernel
def _post(selection, samples, light, radius, taps, seed, color, image):
    """weier2016 section 3.5: a resampled pixel borrows the accumulated light buffer of the closest
    reconstructed pixel among `taps` random taps in a window sized by the nearest reconstructed pixel
    along the image axes."""
    h = selection.flags.shape[0]
    for b in nb.prange((h + ROWS - 1) // ROWS):
        _post_rows(b * ROWS, min(h, (b + 1) * ROWS), selection, samples, light, radius, taps, seed, color, image)


class _EyeState:
    """One eye's history: the camera of its newest frame, its final colour and cache info double-buffered
    (the newest is read while the next is written) and the newest support image and G-buffer."""

    def __init__(self, w: int, h: int, sw: int, sh: int):
        self.size = (w, h, sw, sh)
        self.camera: EyeCamera | None = None
        self.finals = (Final.empty(w, h), Final.empty(w, h))
        self.newest = 0
        self.support = Support.empty(sw, sh)


class _Frame(NamedTuple):
    """What the stages of one frame share: its request, sizes (w, h, sw, sh), buffers, eye state and plan."""

    request: FrameRequest
    size: tuple[int, int, int, int]
    buf: _Buffers
    eye: _EyeState
    history: bool
    steps: tuple[str, ...]
    image: np.ndarray

    @property
    def camera(self) -> EyeCamera:
        return self.request.camera


def _output(out: np.ndarray | None, w: int, h: int) -> np.ndarray:
    """The caller's image buffer, checked, or a new one."""
    if out is None:
        return np.empty((h, w, 3), np.float32)
    if out.shape != (h, w, 3) or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(f"out must be a C-contiguous ({h}, {w}, 3) float32 array, got {out.dtype} {out.shape}")
    return out


class Weier16(Configurable):
    """Foveated ray tracing with coarse-mesh reprojection, resampling info, cache and merge."""

    name = "weier16"
    Params = Weier16Params
    knobs = FOVEAL_REGION_KNOBS
    stages = (
        Stage("reproject", frozenset({HISTORY})),
        Stage("resample_info", frozenset({HISTORY})),
        Stage("sample"),
        Stage("trace"),
        Stage("cache_update"),  # with the reprojected frame's gather and the merge, in one pass
        Stage("post", frozenset({HISTORY, STOCHASTIC})),
    )

    @classmethod
    def knob_values(cls, params: Weier16Params) -> dict[str, Any]:
        """The fields, with r0, r1 and p_min as the frc preset resolves them."""
        return msgspec.structs.asdict(params) | params.foveal()._asdict()

    def __init__(self, tracer: Whitted, params: Weier16Params):
        self.tracer = tracer
        self.features = scene_features(tracer)
        self._eyes: dict[str, _EyeState] = {}
        self._buffers: _Buffers | None = None
        self._gbuffers = GBufferPool()
        self._configure(params)

    def _configure(self, params: Weier16Params) -> None:
        """Keeps each eye's final colour, cache info and support G-buffer: a new foveal region (frc, r0,
        r1, p_min) or new thresholds act on the next frame's samples and cache update, which reprojects
        the cache as usual. A new support size (support_w, support_h) cannot use the previous support
        G-buffer as its coarse mesh, so the next frame starts without history."""
        foveal = params.foveal()
        self.params, self.foveal = params, foveal

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        f = self._frame(request, out)
        mesh = self._reproject(f, stats)
        resample = self._resample_info(f, stats)
        n, xy, keys, light = self._sample(f, mesh, resample, stats)
        samples, normals = self._trace(f, xy, keys, light, stats)
        self._cache_update(f, mesh, n, samples, normals, stats)
        self._post(f, samples, stats)
        f.eye.camera, f.eye.newest = f.request.camera, 1 - f.eye.newest
        sel = f.buf.selection
        stats.metrics["sample_fraction"] = n / (f.size[0] * f.size[1])
        stats.metrics["resampled_pixels"] = int(sel.resampled.sum())
        stats.metrics["support_rays"] = f.size[2] * f.size[3]
        stats.metrics["merged_pixels"] = int(sel.merged.sum())
        return f.image

    def _frame(self, request: FrameRequest, out: np.ndarray | None) -> _Frame:
        """The frame's buffers and history: an eye without a previous frame of this size starts afresh."""
        cam = request.camera
        size = (cam.width, cam.height, *support_size(self.params, cam.width, cam.height))
        image = _output(out, cam.width, cam.height)
        if self._buffers is None or self._buffers.size != size:
            self._buffers = _Buffers(*size)
        eye = self._eyes.get(request.eye)
        history = eye is not None and eye.size == size and eye.camera is not None
        if not history:
            eye = self._eyes[request.eye] = _EyeState(*size)
        steps = plan(self.stages, self.features | ({HISTORY} if history else set()))
        return _Frame(request, size, self._buffers, eye, history, steps, image)

    def _reproject(self, f: _Frame, stats: FrameStats) -> MeshImage:
        """Section 3.2: the previous frame through the coarse mesh of its support G-buffer, at full resolution."""
        if "reproject" not in f.steps:
            return f.buf.mesh.image
        w, h = f.size[:2]
        with stats.stage("reproject"):
            return f.buf.mesh.reproject(f.eye.camera, f.buf.grid_x, f.buf.grid_y, f.eye.support.depth, f.camera, w, h)

    def _resample_info(self, f: _Frame, stats: FrameStats) -> np.ndarray:
        """Section 3.3: the support cells to sample afresh (the no-history stand-in without a previous frame)."""
        if "resample_info" not in f.steps:
            return f.buf.no_resample
        w, h, sw, sh = f.size
        buf, eye, p = f.buf, f.eye, self.params
        with stats.stage("resample_info"):
            low = buf.low_mesh.reproject(eye.camera, buf.grid_x, buf.grid_y, eye.support.depth, f.camera, sw, sh)
            eps = Thresholds(p.eps_depth, p.eps_lum, p.eps_edge)
            low_cam = camera_arrays(f.camera, sw, sh)
            _resampling_info(
                low, low_cam, eye.support, eye.camera.position, float(w), float(h), eps, buf.low_scratch, buf.resample
            )
            return buf.resample

    def _sample(
        self, f: _Frame, mesh: MeshImage, resample: np.ndarray, stats: FrameStats
    ) -> tuple[int, np.ndarray, np.ndarray, LightBuffer]:
        """Section 3.4: how many pixels to trace (foveal probability, resampling info, uncovered pixels), and
        the tracer's sample list: those pixels, then the support grid."""
        buf, request, sel = f.buf, f.request, f.buf.selection
        sw, sh = f.size[2:]
        with stats.stage("sample"):
            ecc = eccentricity_map(f.camera, request.gaze)
            zinv = mesh.zinv if f.history else buf.no_zinv
            dynamic(_select, ecc, self.foveal, request.seed, request.frame, zinv, resample, buf.low_cols, sel)
            np.cumsum(sel.counts, out=sel.row_start[1:])
            n = int(sel.row_start[-1])
            xy, keys, light = buf.sample_list(n + sw * sh)
            key = (request.seed << 32) + request.frame * (1 << 22)
            _fill_samples(sel.flags, sel.row_start, buf.grid_x, buf.grid_y, key, xy, keys)
            return n, xy, keys, light

    def _trace(
        self, f: _Frame, xy: np.ndarray, keys: np.ndarray, light: LightBuffer, stats: FrameStats
    ) -> tuple[Samples, np.ndarray]:
        """The samples' colour, depth and light buffer, and their geometric normals (n, 3)."""
        w, h, sw, sh = f.size
        stochastic = STOCHASTIC in self.features
        with stats.stage("trace"):
            gbuf, rgb = self._gbuffers.rows(len(xy), most=w * h + sw * sh)
            self.tracer.trace_samples(f.camera, xy, keys, stats, gbuf, light if stochastic else None, rgb)
        return Samples(rgb, gbuf.primary.depth, light.irradiance, light.albedo), gbuf.primary.normal_geometric

    def _cache_update(
        self, f: _Frame, mesh: MeshImage, n: int, samples: Samples, normals: np.ndarray, stats: FrameStats
    ) -> None:
        """Sections 3.1 and 3.4: the new support image and G-buffer, then the reprojected frame's gather, the
        merge of the new samples and the running estimate, in one pass into the final colour and the image."""
        p, t, support = self.params, f.request.frame, f.eye.support
        sw, sh = f.size[2:]
        previous, final = f.eye.finals[f.eye.newest], f.eye.finals[1 - f.eye.newest]
        with stats.stage("cache_update"):
            np.copyto(support.depth, samples.depth[n:].reshape(sh, sw))
            np.copyto(support.normal, normals[n:].reshape(sh, sw, 3))
            np.copyto(support.color, samples.rgb[n:].reshape(sh, sw, 3))
            stochastic = STOCHASTIC in self.features
            rule = CacheRule(
                float(t), p.k_min, p.k_max, p.t_max, p.eps_cache, p.footprint_samples, f.request.seed + t, stochastic
            )
            footprints = f.buf.footprints
            dynamic(
                _update, f.buf.selection, mesh, camera_arrays(f.camera), previous, samples, support.color, rule,
                footprints, final, f.image,
            )  # fmt: skip

    def _post(self, f: _Frame, samples: Samples, stats: FrameStats) -> None:
        """Section 3.5: the post filter over the stochastic light buffer, outside the samples traced this frame."""
        p = self.params
        if not (p.post and "post" in f.steps):
            return
        final = f.eye.finals[1 - f.eye.newest]
        with stats.stage("post"):
            seed = f.request.seed + f.request.frame
            dynamic(
                _post, f.buf.selection, samples, final.light, p.post_radius, p.post_samples, seed, final.color, f.image
            )
