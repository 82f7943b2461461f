"""What weier16's stages share (weier2016): the support G-buffer (section 3.1), the final colour, cache info and
light buffer (sections 3.4-3.5), the frame's selection and samples, each stage's rules, and the buffers a frame of
one size works in, kept across frames."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.stages.reproject import CoarseMesh
from hmdrt.foveation.weier16.params import INFO
from hmdrt.trace.gbuffer import LightBuffer


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
