"""Refresh Rate Modulation (smith2013 section 3.2.1).

A foveal rectangle around the fixation is ray traced every frame. The periphery is split into pixel
blocks of `block` consecutive pixels, grouped into refresh cycle groups of group_w x group_h blocks
(default 3 x 4, N = 12); each frame refreshes one block per group, so every peripheral pixel is
refreshed once every N frames, in a refresh order that sets the fragmentation style: horizontal,
serpentine or scattered (hmdrt.foveation.stages.refresh, which also keeps the waits near N while
the budget controller changes N). The rest of the image is a persistent pixel buffer that is never cleared,
so a still scene resolves to the full image after N frames. A fixation smoothing filter sits between
tracker and renderer (section 3.2). The paper gives no size for the foveal rectangle; ours spans
+-fovea_deg around the fixation at the display's central pixel density.

A frame lists only the pixels it refreshes (its cell's blocks on every group_h-th row, and the rectangle) into
persistent sample arrays, never a full-image mask, and one pass writes them into the buffer and the buffer
into the caller's image.
"""

from __future__ import annotations

import math
from typing import Annotated, NamedTuple

import msgspec
import numba as nb
import numpy as np

from hmdrt.foveation.base import Checks, Configurable, FrameRequest, Knob, Stage
from hmdrt.foveation.registry import register
from hmdrt.foveation.stages.gaze import FixationFilter
from hmdrt.foveation.stages.refresh import Order, RefreshSchedule
from hmdrt.foveation.stages.sampling import SMALL_R0, pixels_per_degree
from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.schedule import claim, dynamic
from hmdrt.optics.camera import EyeCamera
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

UPDATE_ROWS = 16  # rows per block of the update kernel
MAX_CYCLE = 20  # the budget controller's largest N = group_w x group_h (Rrm.knobs)


class RrmParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    fovea_deg: Annotated[float, msgspec.Meta(ge=0.0, le=180.0)] = 10.0
    group_w: Annotated[int, msgspec.Meta(ge=1, le=64)] = 3
    group_h: Annotated[int, msgspec.Meta(ge=1, le=64)] = 4
    block: Annotated[int, msgspec.Meta(ge=1, le=64)] = 4
    order: Order = "horizontal"
    smoothing: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.5  # weight of a new fixation; 1 is no smoothing
    saccade_deg: Annotated[float, msgspec.Meta(ge=0.0, le=180.0)] = 3.0

    @property
    def cycle(self) -> int:
        return self.group_w * self.group_h


def foveal_rectangle(camera: EyeCamera, gaze: np.ndarray, params: RrmParams) -> tuple[int, int, int, int]:
    """(x0, x1, y0, y1), half-open, of the foveal rectangle, widened to whole pixel blocks."""
    gx, gy = camera.gaze_pixel(gaze)
    ppd_x, ppd_y = pixels_per_degree(camera)
    hx, hy = params.fovea_deg * ppd_x, params.fovea_deg * ppd_y
    x0 = max(0, int(math.floor((gx - hx) / params.block)) * params.block)
    x1 = min(camera.width, int(math.ceil((gx + hx) / params.block)) * params.block)
    y0, y1 = max(0, int(math.floor(gy - hy))), min(camera.height, int(math.ceil(gy + hy)))
    return x0, max(x0, x1), y0, max(y0, y1)


class Refresh(NamedTuple):
    """The pixels one frame refreshes: its peripheral cell's columns on every group_h-th row from `row`, and the
    foveal rectangle [x0, x1) x [y0, y1) (clamped to the image), in row-major order."""

    cols: np.ndarray  # (k,) int64, ascending: the columns of the blocks of this frame's cell
    row: int  # the first row of this frame's cell; its rows are row, row + group_h, ...
    group_h: int
    x0: int
    x1: int
    y0: int
    y1: int
    width: int
    height: int


class Samples(NamedTuple):
    """Persistent per-frame sample arrays, sized for the most pixels a frame of the current parameters refreshes."""

    xy: np.ndarray  # (capacity, 2) float32 pixel centres
    keys: np.ndarray  # (capacity,) int64 random-stream keys (base.pixel_keys of the pixel index)
    color: np.ndarray  # (capacity, 3) float32: the traced radiance
    row_start: np.ndarray  # (height + 1,) int64: row y's samples are [row_start[y], row_start[y + 1])


def block_columns(width: int, params: RrmParams, cell_x: int) -> np.ndarray:
    """The columns (ascending) whose pixel blocks belong to cycle-group column cell_x."""
    x = np.arange(width)
    return x[(x // params.block) % params.group_w == cell_x]


@serial
def _row_starts(refresh: Refresh, row_start: np.ndarray) -> int:
    """Fills row_start with each row's first sample; returns the sample count."""
    inside = 0  # peripheral columns within the foveal rectangle's
    for x in refresh.cols:
        if refresh.x0 <= x < refresh.x1:
            inside += 1
    fovea, periphery = refresh.x1 - refresh.x0, len(refresh.cols)
    row_start[0] = 0
    for y in range(refresh.height):
        n = 0
        if refresh.y0 <= y < refresh.y1:
            n = fovea
        if y % refresh.group_h == refresh.row:
            n += periphery - inside if n else periphery
        row_start[y + 1] = row_start[y] + n
    return row_start[refresh.height]


@kernel
def _fill(refresh: Refresh, samples: Samples, seed: int) -> None:
    """Each refreshed pixel's centre and key, row by row in row-major order."""
    xy, keys, row_start = samples.xy, samples.keys, samples.row_start  # written in the prange: locals (blocks.py)
    cols, x0, x1, width = refresh.cols, refresh.x0, refresh.x1, refresh.width
    base = np.int64(seed) << np.int64(32)
    for y in nb.prange(refresh.height):
        i = row_start[y]
        periphery = y % refresh.group_h == refresh.row
        fovea = refresh.y0 <= y < refresh.y1
        c = 0
        if periphery:
            while c < len(cols) and (cols[c] < x0 or not fovea):
                i = _put(xy, keys, i, cols[c], y, width, base)
                c += 1
        if fovea:
            for x in range(x0, x1):
                i = _put(xy, keys, i, x, y, width, base)
            if periphery:
                while c < len(cols):
                    if cols[c] >= x1:
                        i = _put(xy, keys, i, cols[c], y, width, base)
                    c += 1


@inline
def _put(xy: np.ndarray, keys: np.ndarray, i: int, x: int, y: int, width: int, base: int) -> int:
    xy[i, 0] = x + 0.5
    xy[i, 1] = y + 0.5
    keys[i] = base + y * width + x
    return i + 1


@kernel
def _update(
    rgb: np.ndarray, samples: Samples, buffer: np.ndarray, out: np.ndarray, counter: np.ndarray, threads: int
) -> None:
    """The traced pixels into the persistent buffer, and the buffer into `out`, a band of rows at a time, bands
    claimed (hmdrt.kernels.schedule: the fovea's bands write many more samples)."""
    xy, row_start = samples.xy, samples.row_start
    h, w = buffer.shape[0], buffer.shape[1]
    # flat views and unsigned indices: no negative-index checks, and the band's copy is one contiguous slice
    flat_buffer, flat_out = buffer.reshape(-1), out.reshape(-1)
    one, two = np.uint64(1), np.uint64(2)
    bands = (h + UPDATE_ROWS - 1) // UPDATE_ROWS
    for _ in nb.prange(threads):
        b = claim(counter)
        while b < bands:
            y0, y1 = b * UPDATE_ROWS, min(h, (b + 1) * UPDATE_ROWS)
            for i in range(row_start[y0], row_start[y1]):
                k = np.uint64((int(xy[i, 1]) * w + int(xy[i, 0])) * 3)
                flat_buffer[k], flat_buffer[k + one], flat_buffer[k + two] = rgb[i, 0], rgb[i, 1], rgb[i, 2]
            lo, hi = np.uint64(y0 * w * 3), np.uint64(y1 * w * 3)
            flat_out[lo:hi] = flat_buffer[lo:hi]
            b = claim(counter)


def _refilter(previous: FixationFilter, params: RrmParams) -> FixationFilter:
    """A fixation filter with params' smoothing that goes on from where `previous` left off."""
    filt = FixationFilter(params.smoothing, params.saccade_deg)
    filt.state = previous.state
    return filt


def most_samples(camera: EyeCamera, params: RrmParams) -> int:
    """An upper bound on the pixels a frame refreshes: every row's share of the periphery plus the largest
    foveal rectangle, so that the sample arrays grow only when the parameters or the image size change."""
    ppd_x, ppd_y = pixels_per_degree(camera)
    w, h = camera.width, camera.height
    fovea_w = min(w, (math.ceil(2 * params.fovea_deg * ppd_x / params.block) + 1) * params.block)
    fovea_h = min(h, math.ceil(2 * params.fovea_deg * ppd_y) + 1)
    periphery = -(-h // params.group_h) * -(-w // (params.block * params.group_w)) * params.block
    return min(w * h, periphery + fovea_w * fovea_h)


@register
class Rrm(Configurable):
    """Refresh Rate Modulation over a persistent pixel buffer per eye."""

    name = "rrm"
    Params = RrmParams
    # the fovea down to weier2016's small region (5 deg), and group_w up until N = group_w x group_h reaches 20,
    # the largest N whose fragmentation smith2013's user study (section 4, Figure 10) did not find noticeable
    knobs = (
        Knob("fovea_deg", SMALL_R0, foveal=True),
        Knob("group_w", lambda v: MAX_CYCLE // v["group_h"], cheaper="higher"),
    )
    stages = (Stage("fixation_filter"), Stage("schedule"), Stage("trace"), Stage("update", touches=True))
    checks = Checks(golden=("whitted",))

    def __init__(self, tracer: Whitted, params: RrmParams):
        self.tracer = tracer
        self._buffers: dict[str, np.ndarray] = {}
        self._filters: dict[str, FixationFilter] = {}
        self._schedules: dict[str, RefreshSchedule] = {}
        self._cols: dict[tuple[int, int], np.ndarray] = {}  # (width, cell column) -> block_columns
        self._samples: Samples | None = None
        self._configure(params)

    def _configure(self, params: RrmParams) -> None:
        """Keeps the persistent buffers and each eye's smoothed fixation (a new smoothing or saccade_deg
        applies from the next sample). A new cycle (group_w, group_h, block or order) regroups the cells:
        each eye's RefreshSchedule takes the cells holding the stalest pixels first, so every peripheral pixel
        is refreshed within the new N frames, and the buffer shows the older pixels until then. fovea_deg
        needs nothing: the rectangle is placed every frame."""
        self._cols.clear()
        self._filters = {eye: _refilter(f, params) for eye, f in self._filters.items()}
        self.params = params

    @property
    def warmup_frames(self) -> int:
        """The refresh cycle N: from a black buffer, every peripheral pixel has been traced once after N frames."""
        return self.params.cycle

    def _sample_arrays(self, camera: EyeCamera) -> Samples:
        """The persistent sample arrays, grown to most_samples when the parameters or the image need more."""
        s, most = self._samples, most_samples(camera, self.params)
        if s is None or len(s.row_start) != camera.height + 1 or len(s.keys) < most:
            s = self._samples = Samples(
                np.empty((most, 2), np.float32),
                np.empty(most, np.int64),
                np.empty((most, 3), np.float32),
                np.empty(camera.height + 1, np.int64),
            )
        return s

    def _schedule(
        self, camera: EyeCamera, gaze: np.ndarray, frame: int, eye: str
    ) -> tuple[Refresh, tuple[int, int, int, int]]:
        p = self.params
        row, column = self._schedules.setdefault(eye, RefreshSchedule()).cell(frame, camera.width, p)
        key = (camera.width, column)
        if key not in self._cols:
            self._cols[key] = block_columns(camera.width, p, key[1])
        rect = x0, x1, y0, y1 = foveal_rectangle(camera, gaze, p)
        w, h = camera.width, camera.height
        x0, y0 = min(x0, w), min(y0, h)
        refresh = Refresh(self._cols[key], row, p.group_h, x0, min(x1, w), y0, min(y1, h), w, h)
        return refresh, rect

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        cam, p = request.camera, self.params
        shape = (cam.height, cam.width, 3)
        if out is None:
            out = np.empty(shape, np.float32)
        elif out.shape != shape or out.dtype != np.float32:
            raise ValueError(f"out must be a float32 array of shape {shape}, got {out.dtype} {out.shape}")
        with stats.stage("fixation_filter"):
            filt = self._filters.setdefault(request.eye, FixationFilter(p.smoothing, p.saccade_deg))
            gaze = filt(request.gaze)
        with stats.stage("schedule"):
            refresh, (x0, x1, y0, y1) = self._schedule(cam, gaze, request.frame, request.eye)
            samples = self._sample_arrays(cam)
            n = _row_starts(refresh, samples.row_start)
            _fill(refresh, samples, request.seed)
        rgb = self.tracer.trace_samples(cam, samples.xy[:n], samples.keys[:n], stats, out=samples.color[:n])
        with stats.stage("update", touches=2 * rgb.nbytes + 2 * out.nbytes):  # samples into the buffer, it into out
            buffer = self._buffers.get(request.eye)
            if buffer is None or buffer.shape != shape:
                buffer = self._buffers[request.eye] = np.zeros(shape, dtype=np.float32)
            dynamic(_update, rgb, samples, buffer, out)
        stats.metrics["sample_fraction"] = n / (cam.width * cam.height)
        stats.metrics["fovea_pixels"] = (x1 - x0) * (y1 - y0)
        return out
