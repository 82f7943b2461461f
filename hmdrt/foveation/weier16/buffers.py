"""What weier16's stages share (weier2016): the support G-buffer (section 3.1), the final colour, cache info and
light buffer (sections 3.4-3.5), the frame's selection and samples, each stage's rules, and the buffers a frame of
one size works in, kept across frames."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.weier16.params import INFO
from hmdrt.kernels.jit import serial
from hmdrt.trace.gbuffer import LightBuffer


class Support(NamedTuple):
    """A frame's support image and support G-buffer (section 3.1), gathered from its support pixels' samples
    (section 3.4): the colour and light buffer fill what nothing else covers (the merge), depth and normal are
    the next frame's coarse mesh. And which of its cells show the support image's reconstruction where the
    reprojection covers them, for the next frame's resampling info."""

    depth: np.ndarray  # (sh, sw) float32 hit distance
    normal: np.ndarray  # (sh, sw, 3) float32 geometric normal
    color: np.ndarray  # (sh, sw, 3) float32
    light: np.ndarray  # (sh, sw, 3) float32 light buffer irradiance; zero without stochastic lights
    unsampled: np.ndarray  # (sh, sw) uint8: a covered pixel of the cell holds no sample of its own (rho 0)

    @classmethod
    def empty(cls, sw: int, sh: int) -> Support:
        rgb = [np.empty((sh, sw, 3), np.float32) for _ in range(3)]
        return cls(np.empty((sh, sw), np.float32), *rgb, np.empty((sh, sw), np.uint8))


def support_pixels(n: int, size: int) -> np.ndarray:
    """The full-resolution columns (or rows) of a support image `size` wide over `n` pixels: floor((i + 0.5) n /
    size), the pixel under the centre of each support pixel; distinct, as size <= n."""
    return (2 * np.arange(size) + 1) * n // (2 * size)


@serial
def cell_span(i, n, cells):
    """The pixels [start, stop) along an axis of n pixels that lie in cell i of `cells` (pixel p in cell
    p cells // n): the resampling info's cells (section 3.3)."""
    return (i * n + cells - 1) // cells, ((i + 1) * n + cells - 1) // cells


class SupportGrid(NamedTuple):
    """Where the support image lies among the full-resolution pixels (section 3.1: rays are generated for the
    pixels that "belong to the support image's resolution"): a regular subset of them, one ray each."""

    x: np.ndarray  # (sw,) float64 the support columns' pixel centres, the coarse mesh's vertices
    y: np.ndarray  # (sh,) float64 the support rows' pixel centres
    column: np.ndarray  # (w,) int32 the support column each pixel column is, -1 for none
    row: np.ndarray  # (h,) int32 the support row each pixel row is, -1 for none
    u: np.ndarray  # (w,) float64 each pixel column in continuous support coordinates, linear between support
    v: np.ndarray  # (h,) float64 pixels (i + 0.5 at support column i): the merge's bilinear upsampling

    @classmethod
    def of(cls, w: int, h: int, sw: int, sh: int) -> SupportGrid:
        cols, rows = support_pixels(w, sw), support_pixels(h, sh)
        column, row = np.full(w, -1, np.int32), np.full(h, -1, np.int32)
        column[cols], row[rows] = np.arange(sw), np.arange(sh)
        u = np.interp(np.arange(w), cols, np.arange(sw)) + 0.5
        v = np.interp(np.arange(h), rows, np.arange(sh)) + 0.5
        return cls(cols + 0.5, rows + 0.5, column, row, u, v)


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

    flags: np.ndarray  # (h, w) uint8: TRACED, FRESH, RESAMPLE, COVERED, FOVEA, SUPPORT, SHOWN
    counts: np.ndarray  # (h,) int64 traced pixels per row
    row_start: np.ndarray  # (h + 1,) int64: the first sample of each row
    resampled: np.ndarray  # (h,) int64 pixels per row marked in the resampling info
    merged: np.ndarray  # (h,) int64 pixels per row taken from the support image


class Samples(NamedTuple):
    """The frame's traced samples, one per traced pixel (the support image's among them) in scanline order."""

    rgb: np.ndarray  # (n, 3) float32
    depth: np.ndarray  # (n,) float32 primary hit distance
    light: np.ndarray  # (n, 3) float32 light buffer irradiance; zero without stochastic lights
    albedo: np.ndarray  # (n, 3) float32 light buffer albedo


class Surfaces(NamedTuple):
    """Which sample each traced pixel took and the surfaces the samples hit: what section 3.5's donors are
    matched by."""

    index: np.ndarray  # (h, w) int32: the sample of each traced pixel (left as it was elsewhere)
    depth: np.ndarray  # (n,) float32 primary hit distance
    normal: np.ndarray  # (n, 3) float32 geometric normal, zero on a miss


class InfoRule(NamedTuple):
    """Section 3.3's resampling thresholds, the motion below which a cell is not tested, and section 3.2's
    footprint filter at the support resolution."""

    depth: float
    lum: float
    edge: float
    motion: float  # full-resolution pixels
    taps: np.ndarray  # (footprint_samples, 2) float64 normally distributed offsets, the same for every cell


class InfoScratch(NamedTuple):
    """The resampling info's working buffers at the support resolution."""

    covered: np.ndarray  # (sh, sw) uint8: the reprojection covers the cell
    moved: np.ndarray  # (sh, sw) uint8: its reprojection moved by more than InfoRule.motion
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
    in_place: bool  # the mesh reprojects each covered pixel onto itself: the final buffers are the previous ones
    ages: np.ndarray  # (AGES,) float64 k_of_age at each whole age (temporal.age_table), kept while the params stay


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
    across frames: the resampling info, the selection, the sample list given to the tracer and where the support
    image lies. Replaced when the image or the support size changes."""

    def __init__(self, w: int, h: int, sw: int, sh: int):
        self.size = (w, h, sw, sh)
        self.resample = np.empty((sh, sw), bool)
        self.taps = RowTaps.empty(w)  # its spread row is also the resampling info's footprints row
        self.low_scratch = InfoScratch(
            np.empty((sh, sw), np.uint8), np.empty((sh, sw), np.uint8), np.empty((sh, sw), np.float32), self.taps.spread
        )
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
        self.listed = np.empty((nb.config.NUMBA_NUM_THREADS, w), np.uint32)  # a row's traced columns (_fill_samples)
        self.cell_rows = np.empty((nb.config.NUMBA_NUM_THREADS, w), np.uint8)  # a cell row's flags (_unsampled_cells)
        self.grid = SupportGrid.of(w, h, sw, sh)
        # the sample list for the most a frame can trace, every pixel: pages a frame never reaches are never
        # touched, so this costs memory only as far as frames fill it
        most = w * h
        self.xy, self.keys = np.empty((most, 2), np.float32), np.empty(most, np.int64)
        self.light = LightBuffer.empty(most)  # zeros: without stochastic lights the tracer leaves it so

    def sample_list(self, n: int) -> tuple[np.ndarray, np.ndarray, LightBuffer]:
        """xy, keys and light buffer rows for n samples."""
        return self.xy[:n], self.keys[:n], LightBuffer(self.light.irradiance[:n], self.light.albedo[:n])
