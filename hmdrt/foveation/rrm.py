"""Refresh Rate Modulation (smith2013 section 3.2.1).

A foveal rectangle around the fixation is ray traced every frame. The periphery is split into pixel
blocks of `block` consecutive pixels, grouped into refresh cycle groups of group_w x group_h blocks
(default 3 x 4, N = 12); each frame refreshes one block per group, so every peripheral pixel is
refreshed once every N frames, in a refresh order that sets the fragmentation style: horizontal,
serpentine or scattered. The rest of the image is a persistent pixel buffer that is never cleared,
so a still scene resolves to the full image after N frames. A fixation smoothing filter sits between
tracker and renderer (section 3.2). The paper gives no size for the foveal rectangle; ours spans
+-fovea_deg around the fixation at the display's central pixel density.
"""

from __future__ import annotations

import math
from typing import Annotated, Literal

import msgspec
import numpy as np

from hmdrt.foveation.base import Configurable, FrameRequest, Stage, pixel_keys
from hmdrt.foveation.stages.gaze import FixationFilter
from hmdrt.foveation.stages.sampling import pixels_per_degree
from hmdrt.optics.camera import EyeCamera
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

Order = Literal["horizontal", "serpentine", "scattered"]


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


def visit_order(group_w: int, group_h: int, order: Order) -> np.ndarray:
    """The cells of a cycle group (row-major indices) in the order they are refreshed.

    horizontal: row by row, left to right. serpentine: row by row, alternating direction. scattered:
    a stride through the cells coprime to N and near N / golden ratio, so consecutive refreshes are far apart.
    """
    n = group_w * group_h
    if order == "horizontal":
        return np.arange(n)
    if order == "serpentine":
        rows = [np.arange(r * group_w, (r + 1) * group_w) for r in range(group_h)]
        return np.concatenate([row if r % 2 == 0 else row[::-1] for r, row in enumerate(rows)])
    target = n / 1.618033988749895
    stride = min((s for s in range(1, n + 1) if math.gcd(s, n) == 1), key=lambda s: (abs(s - target), s))
    return (np.arange(n) * stride) % n


def refresh_phase(width: int, height: int, params: RrmParams) -> np.ndarray:
    """(height, width) int: the frame phase (0 .. N-1) at which each peripheral pixel is refreshed."""
    rank = np.empty(params.cycle, dtype=np.int32)
    rank[visit_order(params.group_w, params.group_h, params.order)] = np.arange(params.cycle)
    bx = (np.arange(width) // params.block) % params.group_w
    by = np.arange(height) % params.group_h
    return rank[by[:, None] * params.group_w + bx[None, :]]


def foveal_rectangle(camera: EyeCamera, gaze: np.ndarray, params: RrmParams) -> tuple[int, int, int, int]:
    """(x0, x1, y0, y1), half-open, of the foveal rectangle, widened to whole pixel blocks."""
    gx, gy = camera.gaze_pixel(gaze)
    ppd_x, ppd_y = pixels_per_degree(camera)
    hx, hy = params.fovea_deg * ppd_x, params.fovea_deg * ppd_y
    x0 = max(0, int(math.floor((gx - hx) / params.block)) * params.block)
    x1 = min(camera.width, int(math.ceil((gx + hx) / params.block)) * params.block)
    y0, y1 = max(0, int(math.floor(gy - hy))), min(camera.height, int(math.ceil(gy + hy)))
    return x0, max(x0, x1), y0, max(y0, y1)


def _refilter(previous: FixationFilter, params: RrmParams) -> FixationFilter:
    """A fixation filter with params' smoothing that goes on from where `previous` left off."""
    filt = FixationFilter(params.smoothing, params.saccade_deg)
    filt.state = previous.state
    return filt


class Rrm(Configurable):
    """Refresh Rate Modulation over a persistent pixel buffer per eye."""

    name = "rrm"
    Params = RrmParams
    stages = (Stage("fixation_filter"), Stage("schedule"), Stage("trace"), Stage("update"))

    def __init__(self, tracer: Whitted, params: RrmParams):
        self.tracer = tracer
        self._buffers: dict[str, np.ndarray] = {}
        self._filters: dict[str, FixationFilter] = {}
        self._phase: dict[tuple[int, int], np.ndarray] = {}  # by image shape, for _schedule
        self._schedule: tuple | None = None
        self._configure(params)

    def _configure(self, params: RrmParams) -> None:
        """Keeps the persistent buffers and each eye's smoothed fixation (a new smoothing or saccade_deg
        applies from the next sample). A new cycle (group_w, group_h, block or order) rebuilds the refresh
        phase maps: every peripheral pixel is then refreshed within the new N frames, and the buffer shows
        the older pixels until then. fovea_deg needs nothing: the rectangle is placed every frame."""
        schedule = (params.group_w, params.group_h, params.block, params.order)
        if schedule != self._schedule:
            self._phase.clear()
        self._schedule = schedule
        self._filters = {eye: _refilter(f, params) for eye, f in self._filters.items()}
        self.params = params

    def render(self, request: FrameRequest, stats: FrameStats) -> np.ndarray:
        cam, p = request.camera, self.params
        with stats.stage("fixation_filter"):
            filt = self._filters.setdefault(request.eye, FixationFilter(p.smoothing, p.saccade_deg))
            gaze = filt(request.gaze)
        with stats.stage("schedule"):
            shape = (cam.height, cam.width)
            if shape not in self._phase:
                self._phase[shape] = refresh_phase(cam.width, cam.height, p)
            mask = self._phase[shape] == request.frame % p.cycle
            x0, x1, y0, y1 = foveal_rectangle(cam, gaze, p)
            mask[y0:y1, x0:x1] = True
            pixels = np.flatnonzero(mask)
            xy = np.empty((len(pixels), 2), dtype=np.float32)
            xy[:, 0] = pixels % cam.width + 0.5
            xy[:, 1] = pixels // cam.width + 0.5
        rgb = self.tracer.trace_samples(cam, xy, pixel_keys(pixels, request.seed), stats)
        with stats.stage("update"):
            buffer = self._buffers.get(request.eye)
            if buffer is None or buffer.shape[:2] != shape:
                buffer = self._buffers[request.eye] = np.zeros((*shape, 3), dtype=np.float32)
            buffer.reshape(-1, 3)[pixels] = rgb
        stats.metrics["sample_fraction"] = len(pixels) / mask.size
        stats.metrics["fovea_pixels"] = (x1 - x0) * (y1 - y0)
        return buffer.copy()
