"""Foveated real-time ray tracing with reprojection (weier2016).

Section 3.1: pixels are traced when xi_q < p(q), the foveal function of the foveal region
configuration (r0, r1, p_min); a low-resolution support image and support G-buffer (256 x 318 at
DK2's 1182 x 1464, scaled with the profile) are traced every frame. Section 3.2: the previous final
colour and cache info are reprojected through a coarse mesh built from the previous support G-buffer
(unprojected with the previous camera, projected with the current one), filtering each pixel's
footprint. Section 3.3: the resampling info renders that reprojection at the support resolution and marks
cells whose depth departs from their direct neighbourhood (a second difference of 1/z above eps_depth), whose
luminance contrast to a neighbour exceeds eps_lum, or whose previous surface is seen at a grazing angle
(edge_t = max(n.d, 0) < eps_edge); their pixels are traced. Section 3.4: samples in the fovea, in resampled
cells, where nothing was reprojected, or whose depth disagrees with the cache by more than eps_cache, replace
the cache; the others update it with the running estimate (alpha, rho) bounded below by k(dt) between k_min
and k_max over t_max frames. Pixels left without colour are merged from the support image, colour and light
buffer. Section 3.5: when the scene has area lights or ambient occlusion, a resampled pixel outside the fovea
takes the accumulated light buffer of the closest reconstructed pixel found by n random taps in a window sized
by the nearest one along the image axes; a reconstructed pixel is one traced this frame and merged into its
cache, on the pixel's surface. The filter changes the image shown, not the cache.

Each frame reprojects the mesh, marks the resampling info, selects and traces the samples, then runs
one pass that gathers the previous frame through the mesh, applies the running estimate and merges,
reading one of two persistent final buffers per eye and writing the other and the caller's image;
nothing of the image's size is allocated per frame.

Values the paper leaves open (eps_*, k_min, k_max, t_max, footprint taps, post taps and its surface test) are
parameters with defaults chosen here. Section 3.4 prints alpha = min(alpha', k); the running estimate uses
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
    gaussian_taps,
    nearest_texel,
    row_footprints,
)
from hmdrt.foveation.stages.sampling import FOVEAL_REGION_KNOBS, Foveal, foveal_config, foveal_probability
from hmdrt.foveation.stages.temporal import k_of_age, running_estimate
from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.rng import uniform
from hmdrt.kernels.schedule import claim, dynamic
from hmdrt.optics.camera import EyeCamera, eccentricity_map
from hmdrt.optics.projection import (
    FAR,
    bilinear3,
    bilinear_footprint,
    blend_footprint,
    camera_arrays,
    view_distance,
    view_point,
    world_point,
)
from hmdrt.ranges import Deg, Fraction
from hmdrt.telemetry.stats import FrameStats, nbytes
from hmdrt.trace.gbuffer import GBufferPool, LightBuffer
from hmdrt.trace.integrator import Whitted

DK2_SUPPORT = (256, 318, 1182, 1464)  # section 4.1: a 256 x 318 support image at 1182 x 1464
INFO = 3  # cache info per pixel: alpha, rho and the frame it was last touched
TRACED, FRESH, RESAMPLE, COVERED, FOVEA = 1, 2, 4, 8, 16  # a pixel's flags: traced this frame; its sample
# replaces the cache (fovea or resampled); marked in the resampling info; covered by the reprojected mesh;
# inside r0
SUPPORT_STREAM = 2 << 40  # base.pixel_keys stream 2: the support image's samples


class Weier16Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    frc: Literal["small", "medium", "large", "full"] = "medium"
    r0: Deg | None = None
    r1: Deg | None = None
    p_min: Fraction | None = None
    support_w: Annotated[int, msgspec.Meta(ge=2, le=4096)] | None = None
    support_h: Annotated[int, msgspec.Meta(ge=2, le=4096)] | None = None
    eps_depth: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.05  # second difference of 1/z, relative
    eps_lum: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.2  # luminance contrast |a - b| / (a + b)
    eps_edge: Fraction = 0.1  # grazing angle: edge_t = max(n.d, 0) below this
    eps_cache: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.05  # relative depth, cache vs new sample
    k_min: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.1
    k_max: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.5  # configs/eval/weier16_cache.toml
    t_max: Annotated[float, msgspec.Meta(ge=1.0, le=1e6)] = 30.0
    footprint_samples: Annotated[int, msgspec.Meta(ge=1, le=64)] = 4
    post: bool = True
    post_samples: Annotated[int, msgspec.Meta(ge=1, le=256)] = 8
    post_radius: Annotated[int, msgspec.Meta(ge=1, le=1024)] = 32  # pixels searched along each axis
    post_depth: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.02  # donor off the pixel's tangent plane
    post_normal: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)] = 0.9  # least cosine between their normals

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
    """A frame's support G-buffer (section 3.1), the next frame's coarse mesh. (The support image itself is the
    tail of the frame's samples.)"""

    depth: np.ndarray  # (sh, sw) float32 hit distance
    normal: np.ndarray  # (sh, sw, 3) float32 geometric normal

    @classmethod
    def empty(cls, sw: int, sh: int) -> Support:
        return cls(np.empty((sh, sw), np.float32), np.empty((sh, sw, 3), np.float32))


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

    flags: np.ndarray  # (h, w) uint8: TRACED, FRESH, RESAMPLE, COVERED, FOVEA
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


class Surfaces(NamedTuple):
    """Which sample each traced pixel took and the surfaces the samples hit: what section 3.5's donors are
    matched by."""

    index: np.ndarray  # (h, w) int32: the sample of each traced pixel (left as it was elsewhere)
    depth: np.ndarray  # (n + support,) float32 primary hit distance
    normal: np.ndarray  # (n + support, 3) float32 geometric normal, zero on a miss


class InfoRule(NamedTuple):
    """Section 3.3's resampling thresholds and section 3.2's footprint filter at the support resolution."""

    depth: float
    lum: float
    edge: float
    taps: np.ndarray  # (footprint_samples, 2) float64 normally distributed offsets, the same for every cell


class InfoScratch(NamedTuple):
    """The resampling info's working buffers at the support resolution."""

    covered: np.ndarray  # (sh, sw) uint8: the reprojection covers the cell
    lum: np.ndarray  # (sh, sw) float32 luminance of the reprojected final colour
    footprints: np.ndarray  # (threads, >= sw) float32: a row's footprints, per thread


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


class RowTaps(NamedTuple):
    """The cache update's scratch, a row per numba thread (nb.get_thread_id()): each pixel's footprint spread
    (row_footprints) and the bilinear footprint of its reprojection in the previous final colour
    (projection.bilinear_footprint), taken for a whole row in passes that vectorise before the pixels' loop."""

    spread: np.ndarray  # (threads, >= w) float32
    weights: np.ndarray  # (threads, 2, w) float64: across, down
    index: np.ndarray  # (threads, 3, w) uint64: top-left element, step right, step down

    @classmethod
    def empty(cls, w: int) -> RowTaps:
        threads = nb.config.NUMBA_NUM_THREADS
        return cls(np.empty((threads, w), np.float32), np.empty((threads, 2, w)), np.empty((threads, 3, w), np.uint64))


class PostRule(NamedTuple):
    """Section 3.5's search, and the surface test a donor must pass (the paper gives none)."""

    radius: int  # pixels searched along each axis
    taps: int
    seed: int
    plane: float  # the donor's hit at most this fraction of the pixel's distance off the pixel's tangent plane
    normal: float  # the least cosine between their geometric normals


class _Buffers:
    """Everything a frame of one size works in, shared by the eyes (they render one after the other), kept
    across frames: the two coarse meshes, the resampling info, the selection, the sample list given to the
    tracer and the geometry of the support grid. Replaced when the image or the support size changes."""

    def __init__(self, w: int, h: int, sw: int, sh: int):
        self.size = (w, h, sw, sh)
        self.mesh = CoarseMesh()  # at full resolution
        self.low_mesh = CoarseMesh()  # at support resolution, for the resampling info
        self.resample = np.empty((sh, sw), bool)
        self.taps = RowTaps.empty(w)  # its spread row is also the resampling info's footprints row
        self.low_scratch = InfoScratch(np.empty((sh, sw), np.uint8), np.empty((sh, sw), np.float32), self.taps.spread)
        self.no_resample = np.zeros((0, 0), bool)  # stand-ins for a frame without history
        self.no_zinv = np.zeros((0, 0), np.float32)
        self.selection = Selection(
            np.empty((h, w), np.uint8),
            np.empty(h, np.int64),
            np.zeros(h + 1, np.int64),
            np.empty(h, np.int64),
            np.empty(h, np.int64),
        )
        self.sample_index = np.empty((h, w), np.int32)
        self.draws = np.empty((nb.config.NUMBA_NUM_THREADS, w))  # a row's random numbers per thread (_select)
        self.grid_x, self.grid_y = (np.arange(sw) + 0.5) * w / sw, (np.arange(sh) + 0.5) * h / sh
        self.low_cols = np.arange(w) * sw // w  # the support column each pixel's resampling info comes from
        # the sample list for the most a frame can trace, every pixel and the support image: pages a frame
        # never reaches are never touched, so this costs memory only as far as frames fill it
        most = w * h + sw * sh
        self.xy, self.keys = np.empty((most, 2), np.float32), np.empty(most, np.int64)
        self.light = LightBuffer.empty(most)  # zeros: without stochastic lights the tracer leaves it so

    def sample_list(self, n: int) -> tuple[np.ndarray, np.ndarray, LightBuffer]:
        """xy, keys and light buffer rows for n samples."""
        return self.xy[:n], self.keys[:n], LightBuffer(self.light.irradiance[:n], self.light.albedo[:n])


@serial
def _footprint_mean(color, qx, qy, spread, taps):
    """Section 3.2's footprint filter of the previous final colour at (qx, qy), spread: the footprint's width in
    its pixels: bilinear about a pixel wide, else the mean of bilinear taps at offsets sigma = spread / 2 times
    `taps` (k, 2), one normally distributed pattern for every cell (no random numbers drawn per cell)."""
    if spread <= 1.5:
        return bilinear3(color, qx, qy)
    sigma, n = 0.5 * spread, taps.shape[0]
    r = g = b = 0.0
    for k in range(n):
        sr, sg, sb = bilinear3(color, qx + sigma * taps[k, 0], qy + sigma * taps[k, 1])
        r, g, b = r + sr, g + sg, b + sb
    return r / n, g / n, b / n


@serial
def _luminance_rows(y0, y1, prev, color, rule, scratch):
    """Rows [y0, y1) of the reprojected final colour's luminance at the support resolution (section 3.3 renders
    the coarse mesh at that resolution with section 3.2's procedure), NaN where the mesh leaves a cell."""
    covered, lum = scratch.covered, scratch.lum
    h, w = lum.shape
    spread = scratch.footprints[nb.get_thread_id()]
    for y in range(y0, y1):
        row_footprints(prev, covered, 1, y, spread)
        for x in range(w):
            if not covered[y, x]:
                lum[y, x] = math.nan
                continue
            r, g, b = _footprint_mean(color, prev[0, y, x], prev[1, y, x], spread[x], rule.taps)
            lum[y, x] = 0.2126 * r + 0.7152 * g + 0.0722 * b


@serial
def _bent(a, b, c, eps):
    """Section 3.3's depth test along one axis: 1/z, affine across a plane in the image (the mesh interpolates
    it so), departs at b from the line through its neighbours a and c by more than eps of b's. A plane gives
    0 however slanted; a depth jump to one neighbour by more than eps of the depth trips it."""
    return abs(a - 2.0 * b + c) > eps * b


@serial
def _contrast(a, b, eps):
    """Section 3.3's luminance test between two cells: |a - b| / (a + b) above eps; NaN (uncovered) never."""
    return a + b > 0.0 and abs(a - b) > eps * (a + b)


@serial
def _discontinuous(zinv, covered, lum, y, x, rule):
    """Section 3.3: a depth or luminance difference between cell (y, x) and its direct neighbourhood in the
    reprojected image."""
    h, w = zinv.shape
    z = zinv[y, x]
    if (
        0 < x < w - 1
        and covered[y, x - 1]
        and covered[y, x + 1]
        and _bent(zinv[y, x - 1], z, zinv[y, x + 1], rule.depth)
    ):
        return True
    if (
        0 < y < h - 1
        and covered[y - 1, x]
        and covered[y + 1, x]
        and _bent(zinv[y - 1, x], z, zinv[y + 1, x], rule.depth)
    ):
        return True
    la = lum[y, x]
    return (
        (x + 1 < w and _contrast(la, lum[y, x + 1], rule.lum))
        or (x > 0 and _contrast(la, lum[y, x - 1], rule.lum))
        or (y + 1 < h and _contrast(la, lum[y + 1, x], rule.lum))
        or (y > 0 and _contrast(la, lum[y - 1, x], rule.lum))
    )


@inline
def _grazing(mesh, cur, normal, prev_position, x, y, full_w, full_h, eps):
    """Section 3.3's edge test: edge_t = max(n.d, 0) < eps with the previous frame's geometric normal n and the
    direction d to its eye, at cell (y, x); never where the support G-buffer holds no normal (a miss)."""
    prev = mesh.prev
    ph, pw = normal.shape[0], normal.shape[1]
    sx = min(max(int(prev[0, y, x] * pw / full_w), 0), pw - 1)
    sy = min(max(int(prev[1, y, x] * ph / full_h), 0), ph - 1)
    nx, ny, nz = normal[sy, sx, 0], normal[sy, sx, 1], normal[sy, sx, 2]
    if nx == 0.0 and ny == 0.0 and nz == 0.0:
        return False
    px, py, pz = view_point(cur, x + 0.5, y + 0.5, 1.0 / mesh.zinv[y, x])
    vx, vy, vz = prev_position[0] - px, prev_position[1] - py, prev_position[2] - pz
    inv = 1.0 / max(math.sqrt(vx * vx + vy * vy + vz * vz), 1e-30)
    return max((nx * vx + ny * vy + nz * vz) * inv, 0.0) < eps


@kernel
def _resampling_info(mesh, cur, color, normal, prev_position, full_w, full_h, rule, scratch, out):
    """weier2016 section 3.3 at support resolution: the previous final colour reprojected through the coarse
    mesh; cells with a depth or luminance discontinuity against their neighbourhood, grazing surfaces and
    uncovered cells are marked."""
    zinv, covered = mesh.zinv, scratch.covered  # written through locals: see hmdrt/trace/blocks.py
    h, w = zinv.shape
    for y in nb.prange(h):
        for x in range(w):
            covered[y, x] = 1 if zinv[y, x] > 0.0 else 0
    for b in nb.prange((h + ROWS - 1) // ROWS):
        _luminance_rows(b * ROWS, min(h, (b + 1) * ROWS), mesh.prev, color, rule, scratch)
    lum = scratch.lum
    for y in nb.prange(h):
        for x in range(w):
            out[y, x] = (
                not covered[y, x]
                or _discontinuous(zinv, covered, lum, y, x, rule)
                or _grazing(mesh, cur, normal, prev_position, x, y, full_w, full_h, rule.edge)
            )


@kernel
def _select(ecc, foveal, seed, frame, zinv, resample, low_cols, selection, draws, counter, threads):
    """Section 3.1's ray generation (pixel q traced when xi_q < p(q), sampling.bernoulli_mask's xi) and the
    pixels of cells marked in the resampling info, with each pixel's flags and each row's sample count. The row's
    xi are drawn first, in a loop of their own that vectorises, into the thread's row of `draws`."""
    flags, counts, resampled = selection.flags, selection.counts, selection.resampled
    h, w = flags.shape
    sh = resample.shape[0]
    history = zinv.shape[0] == h
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < h:
            xi, key = draws[nb.get_thread_id()], y * w + (seed << 32)
            for x in range(w):
                xi[x] = uniform(key + x, 0x5A3, frame)
            ly = y * sh // h
            n = nr = 0
            for x in range(w):
                e = ecc[y, x]
                f = COVERED if history and zinv[y, x] > 0.0 else 0
                if e < foveal.r0:
                    f |= FOVEA
                if sh > 0 and resample[ly, low_cols[x]]:
                    f |= TRACED | FRESH | RESAMPLE
                    nr += 1
                elif e < foveal.r0:  # p(q) = 1
                    f |= TRACED | FRESH
                else:
                    p = foveal_probability(e, foveal.r0, foveal.r1, foveal.p_min)
                    if p >= 1.0 or xi[x] < p:
                        f |= TRACED
                flags[y, x] = f
                n += f & TRACED
            counts[y] = n
            resampled[y] = nr
            y = claim(counter)


@kernel
def _fill_samples(flags, row_start, grid_x, grid_y, key_base, xy, keys, index):
    """Pixel centres and random-stream keys of the traced pixels in scanline order, then of the support grid
    (base.pixel_keys: stream 0 for pixels, 2 for the support image); each traced pixel's sample in index."""
    h, w = flags.shape
    for y in nb.prange(h):
        s = row_start[y]
        for x in range(w):
            if flags[y, x] & TRACED:
                xy[s, 0], xy[s, 1] = x + 0.5, y + 0.5
                keys[s] = y * w + x + key_base
                index[y, x] = s
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
def _support_light(light, base, sw, sh, x, y, c):
    """Channel c of the support image's light buffer (sample rows base + j * sw + i) at continuous support
    coordinates (x, y), bilinear and clamped at the border like the merge's colour (bilinear3)."""
    fx, fy = x - 0.5, y - 0.5
    x0, y0 = math.floor(fx), math.floor(fy)
    ax, ay = fx - x0, fy - y0
    i0, j0 = min(max(int(x0), 0), sw - 1), min(max(int(y0), 0), sh - 1)
    i1, j1 = min(max(int(x0) + 1, 0), sw - 1), min(max(int(y0) + 1, 0), sh - 1)
    top = (1.0 - ax) * light[base + j0 * sw + i0, c] + ax * light[base + j0 * sw + i1, c]
    bottom = (1.0 - ax) * light[base + j1 * sw + i0, c] + ax * light[base + j1 * sw + i1, c]
    return (1.0 - ay) * top + ay * bottom


@serial
def _update_rows(y0, y1, selection, mesh, cur, previous, samples, support, rule, taps, final, image):
    flags, row_start = selection.flags, selection.row_start
    prev, zinv = mesh.prev, mesh.zinv
    prev_color, prev_info, prev_light = previous.color, previous.info, previous.light
    rgb, sample_depth, sample_light = samples.rgb, samples.depth, samples.light
    color, info, light = final.color, final.info, final.light
    h, w = flags.shape
    sh, sw = support.shape[0], support.shape[1]
    t = nb.get_thread_id()
    spread_row, across, down = taps.spread[t], taps.weights[t, 0], taps.weights[t, 1]
    corner, step_x, step_y = taps.index[t, 0], taps.index[t, 1], taps.index[t, 2]
    flat = prev_color.reshape(-1)
    history = zinv.shape[0] == h  # else no pixel is covered, and the mesh buffers may be empty
    for y in range(y0, y1):
        if history:
            row_footprints(prev, flags, COVERED, y, spread_row)
            px, py = prev[0, y], prev[1, y]
            for x in range(w):
                across[x], down[x], corner[x], step_x[x], step_y[x] = bilinear_footprint(px[x], py[x], w, h)
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
                    r, g, b = blend_footprint(flat, corner[x], step_x[x], step_y[x], across[x], down[x])
                else:
                    key = (y * w + x) * 64 + rule.seed
                    r, g, b = gaussian_taps(prev_color, qx, qy, 0.5 * spread, rule.footprint_samples, key)
                r, g, b = np.float32(r), np.float32(g), np.float32(b)  # the reprojected image is float32
                jy, jx = nearest_texel(qx, qy, w, h)  # cache info is not blended: the nearest texel
            if traced:
                alpha, rho = 1.0, 1.0
                if not new:
                    k = k_of_age(rule.frame - prev_info[jy, jx, 2], rule.k_min, rule.k_max, rule.t_max)
                    # rho 0: merged from the support image, no sample of this pixel; the new one replaces it
                    alpha, rho = running_estimate(prev_info[jy, jx, 1], k)
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
            else:  # the merge: the bilinearly upsampled support image, colour and light buffer
                lx, ly = (x + 0.5) * sw / w, (y + 0.5) * sh / h
                r, g, b = bilinear3(support, lx, ly)
                color[y, x, 0], color[y, x, 1], color[y, x, 2] = r, g, b
                for c in range(INFO):
                    info[y, x, c] = 0.0
                if rule.stochastic:
                    for c in range(3):
                        light[y, x, c] = _support_light(sample_light, row_start[h], sw, sh, lx, ly, c)
                merged += 1
            for c in range(3):
                image[y, x, c] = color[y, x, c]
        selection.merged[y] = merged


@kernel
def _update(selection, mesh, cur, previous, samples, support, rule, taps, final, image, counter, threads):
    """Sections 3.2 and 3.4 in one pass: each pixel's previous colour and cache info gathered through the
    mesh, its sample merged into them with the running estimate (or replacing them: fovea, resampled,
    uncovered or moved), and pixels left without colour taken from the support image; into the final
    colour, cache info and the caller's image."""
    h = selection.flags.shape[0]
    blocks = (h + ROWS - 1) // ROWS
    for _ in nb.prange(threads):
        b = claim(counter)
        while b < blocks:
            y0, y1 = b * ROWS, min(h, (b + 1) * ROWS)
            _update_rows(y0, y1, selection, mesh, cur, previous, samples, support, rule, taps, final, image)
            b = claim(counter)


@serial
def _lends(flags, info, y, x):
    """Section 3.5's reconstructed pixel, as this filter takes it: traced this frame and merged into its cache
    (its light buffer holds more than one sample)."""
    return flags[y, x] & (TRACED | FRESH) == TRACED and info[y, x, 1] > 1.0


@inline
def _donor(ty, tx, surfaces, cur, q, qx, qy, qz, rule):
    """Whether reconstructed pixel (ty, tx) lies on sample q's surface: its normal within rule.normal of q's
    and its hit point off the plane through q's (qx, qy, qz) by at most rule.plane of q's distance."""
    r, normal = surfaces.index[ty, tx], surfaces.normal
    if normal[q, 0] * normal[r, 0] + normal[q, 1] * normal[r, 1] + normal[q, 2] * normal[r, 2] < rule.normal:
        return False
    px, py, pz = world_point(cur, tx + 0.5, ty + 0.5, surfaces.depth[r])
    off = normal[q, 0] * (px - qx) + normal[q, 1] * (py - qy) + normal[q, 2] * (pz - qz)
    return abs(off) <= rule.plane * surfaces.depth[q]


@inline
def _nearest_on_axes(y, x, flags, info, surfaces, cur, q, qx, qy, qz, rule):
    """Section 3.5: how far the nearest donor (reconstructed, on q's surface) lies along the image axes from
    pixel (y, x), 0 for none within rule.radius."""
    h, w = flags.shape
    # the four neighbours spelled out, _lends inlined by hand: a loop over offsets or a call per neighbour made
    # this search 1.5 to 8 times slower at rift_s (numba's reference counting of the tuples)
    for d in range(1, rule.radius + 1):
        if x + d < w and flags[y, x + d] & (TRACED | FRESH) == TRACED and info[y, x + d, 1] > 1.0:
            if _donor(y, x + d, surfaces, cur, q, qx, qy, qz, rule):
                return d
        if x >= d and flags[y, x - d] & (TRACED | FRESH) == TRACED and info[y, x - d, 1] > 1.0:
            if _donor(y, x - d, surfaces, cur, q, qx, qy, qz, rule):
                return d
        if y + d < h and flags[y + d, x] & (TRACED | FRESH) == TRACED and info[y + d, x, 1] > 1.0:
            if _donor(y + d, x, surfaces, cur, q, qx, qy, qz, rule):
                return d
        if y >= d and flags[y - d, x] & (TRACED | FRESH) == TRACED and info[y - d, x, 1] > 1.0:
            if _donor(y - d, x, surfaces, cur, q, qx, qy, qz, rule):
                return d
    return 0


@inline
def _post_pixel(y, x, flags, surfaces, samples, final, cur, rule, image):
    """Section 3.5 at pixel (y, x): the distance to the nearest donor along the axes sizes a window sampled
    rule.taps times, and the closest donor among the taps lends its accumulated light buffer."""
    h, w = flags.shape
    q = surfaces.index[y, x]
    if surfaces.depth[q] >= FAR:
        return
    qx, qy, qz = world_point(cur, x + 0.5, y + 0.5, surfaces.depth[q])
    info = final.info
    reach = _nearest_on_axes(y, x, flags, info, surfaces, cur, q, qx, qy, qz, rule)
    if reach == 0:
        return
    best, best_d2, i = -1, 1 << 30, y * w + x
    for t in range(rule.taps):
        ox = int(math.floor((2.0 * uniform(i + rule.seed, 11, 2 * t) - 1.0) * reach + 0.5))
        oy = int(math.floor((2.0 * uniform(i + rule.seed, 11, 2 * t + 1) - 1.0) * reach + 0.5))
        ty, tx, d2 = y + oy, x + ox, ox * ox + oy * oy
        if (
            d2 < best_d2
            and 0 <= ty < h
            and 0 <= tx < w
            and _lends(flags, info, ty, tx)
            and _donor(ty, tx, surfaces, cur, q, qx, qy, qz, rule)
        ):
            best, best_d2 = ty * w + tx, d2
    if best < 0:
        return
    by, bx = best // w, best % w
    for c in range(3):
        # the sample's colour minus its own stochastic part is >= 0 exactly; max() only absorbs float rounding
        rest = max(samples.rgb[q, c] - samples.albedo[q, c] * samples.light[q, c], 0.0)
        image[y, x, c] = rest + samples.albedo[q, c] * final.light[by, bx, c]


@serial
def _post_rows(y0, y1, selection, surfaces, samples, final, cur, rule, image):
    flags = selection.flags
    for y in range(y0, y1):
        if not selection.resampled[y]:
            continue
        for x in range(flags.shape[1]):
            if flags[y, x] & (RESAMPLE | FOVEA) == RESAMPLE:
                _post_pixel(y, x, flags, surfaces, samples, final, cur, rule, image)


@kernel
def _post(selection, surfaces, samples, final, cur, rule, image, counter, threads):
    """weier2016 section 3.5 on the image shown: each resampled pixel outside the fovea takes the accumulated
    light buffer of the closest donor found (_post_pixel); the cache keeps the colour before the filter."""
    h = selection.flags.shape[0]
    blocks = (h + ROWS - 1) // ROWS
    for _ in nb.prange(threads):
        b = claim(counter)
        while b < blocks:
            _post_rows(b * ROWS, min(h, (b + 1) * ROWS), selection, surfaces, samples, final, cur, rule, image)
            b = claim(counter)


class _EyeState:
    """One eye's history: the camera of its newest frame, its final colour and cache info double-buffered
    (the newest is read while the next is written) and the newest support G-buffer."""

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
        G-buffer as its coarse mesh, so the next frame starts without history. Draws the resampling info's
        footprint taps (InfoRule.taps)."""
        foveal = params.foveal()
        self.params, self.foveal = params, foveal
        self._taps = np.random.default_rng(0).standard_normal((params.footprint_samples, 2))

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        f = self._frame(request, out)
        mesh = self._reproject(f, stats)
        resample = self._resample_info(f, stats)
        n, xy, keys, light = self._sample(f, mesh, resample, stats)
        samples, normals = self._trace(f, xy, keys, light, stats)
        self._cache_update(f, mesh, n, samples, normals, stats)
        self._post(f, samples, normals, stats)
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
        written = w * h * 3 * np.dtype(np.float32).itemsize  # the mesh image: x, y in the previous frame and 1/z
        with stats.stage("reproject", touches=f.eye.support.depth.nbytes + written):
            return f.buf.mesh.reproject(f.eye.camera, f.buf.grid_x, f.buf.grid_y, f.eye.support.depth, f.camera, w, h)

    def _resample_info(self, f: _Frame, stats: FrameStats) -> np.ndarray:
        """Section 3.3: the support cells to sample afresh (the no-history stand-in without a previous frame)."""
        if "resample_info" not in f.steps:
            return f.buf.no_resample
        w, h, sw, sh = f.size
        buf, eye, p = f.buf, f.eye, self.params
        with stats.stage("resample_info"):
            low = buf.low_mesh.reproject(eye.camera, buf.grid_x, buf.grid_y, eye.support.depth, f.camera, sw, sh)
            rule = InfoRule(p.eps_depth, p.eps_lum, p.eps_edge, self._taps)
            low_cam, previous = camera_arrays(f.camera, sw, sh), eye.finals[eye.newest]
            _resampling_info(
                low, low_cam, previous.color, eye.support.normal, eye.camera.position, float(w), float(h), rule,
                buf.low_scratch, buf.resample,
            )  # fmt: skip
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
            dynamic(
                _select, ecc, self.foveal, request.seed, request.frame, zinv, resample, buf.low_cols, sel, buf.draws
            )
            np.cumsum(sel.counts, out=sel.row_start[1:])
            n = int(sel.row_start[-1])
            xy, keys, light = buf.sample_list(n + sw * sh)
            key = (request.seed << 32) + request.frame * (1 << 22)
            _fill_samples(sel.flags, sel.row_start, buf.grid_x, buf.grid_y, key, xy, keys, buf.sample_index)
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
        """Sections 3.1 and 3.4: the new support G-buffer, then the reprojected frame's gather, the merge of the
        new samples and the running estimate, in one pass into the final colour and the image."""
        p, t, support = self.params, f.request.frame, f.eye.support
        sw, sh = f.size[2:]
        previous, final = f.eye.finals[f.eye.newest], f.eye.finals[1 - f.eye.newest]
        stochastic = STOCHASTIC in self.features
        lights = (previous.light, final.light, samples.light) if stochastic else ()
        touched = (f.buf.selection.flags, *mesh, previous.color, previous.info, final.color, final.info, f.image)
        with stats.stage("cache_update", touches=nbytes(*touched, samples.rgb, samples.depth, *lights)):
            np.copyto(support.depth, samples.depth[n:].reshape(sh, sw))
            np.copyto(support.normal, normals[n:].reshape(sh, sw, 3))
            support_image = samples.rgb[n:].reshape(sh, sw, 3)
            rule = CacheRule(
                float(t), p.k_min, p.k_max, p.t_max, p.eps_cache, p.footprint_samples, f.request.seed + t, stochastic
            )
            dynamic(
                _update, f.buf.selection, mesh, camera_arrays(f.camera), previous, samples, support_image, rule,
                f.buf.taps, final, f.image,
            )  # fmt: skip

    def _post(self, f: _Frame, samples: Samples, normals: np.ndarray, stats: FrameStats) -> None:
        """Section 3.5: the post filter over the stochastic light buffer, on the image shown."""
        p = self.params
        if not (p.post and "post" in f.steps):
            return
        final = f.eye.finals[1 - f.eye.newest]
        with stats.stage("post"):
            rule = PostRule(
                p.post_radius, p.post_samples, f.request.seed + f.request.frame, p.post_depth, p.post_normal
            )
            surfaces = Surfaces(f.buf.sample_index, samples.depth, normals)
            dynamic(_post, f.buf.selection, surfaces, samples, final, camera_arrays(f.camera), rule, f.image)
