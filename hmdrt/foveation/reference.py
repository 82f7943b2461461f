"""The reference renderers every foveated method is measured against.

full: one ray per pixel centre, no foveation. regular: N stratified jittered samples per pixel,
box-filtered; N = 36 is the ground truth of kim2021 section 5 ("36 stratified samples per pixel").
"""

from __future__ import annotations

from typing import Annotated

import msgspec
import numpy as np

from hmdrt.foveation.base import Checks, Configurable, FrameRequest, NoParams, Stage, sample_keys
from hmdrt.foveation.registry import register
from hmdrt.optics.camera import pixel_grid
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.trace.sampling import jittered_pixels

MAX_SPP = 1024


@register
class Full(Configurable):
    """One primary ray through every pixel centre."""

    name = "full"
    Params = NoParams
    stages = (Stage("trace"),)
    checks = Checks(temporal=False)
    warmup_frames = 0  # no history: every frame is rendered afresh

    def __init__(self, tracer: Whitted, params: NoParams):
        self.tracer = tracer
        self._configure(params)

    def _configure(self, params: NoParams) -> None:
        """No parameters; the sample keys of the last (image size, seed) are kept."""
        self.params = params
        self._keys = (None, np.empty(0, np.int64))

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        cam = request.camera
        xy = pixel_grid(cam.width, cam.height)
        if self._keys[0] != (len(xy), request.seed):
            self._keys = ((len(xy), request.seed), sample_keys(0, len(xy), request.seed))
        if out is None:
            out = np.empty((cam.height, cam.width, 3), np.float32)
        self.tracer.trace_samples(cam, xy, self._keys[1], stats, out=out.reshape(-1, 3))
        return out


class RegularParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    spp: Annotated[int, msgspec.Meta(ge=1, le=MAX_SPP)] = 36


@register
class Regular(Configurable):
    """spp stratified jittered samples per pixel, averaged (a box filter over the pixel)."""

    name = "regular"
    Params = RegularParams
    stages = (Stage("trace"), Stage("resolve"))
    checks = Checks(golden=(), bench=False, temporal=False)  # the ground truth: the eval and the benches score
    # against it (bench/foveation_speedup.py renders it beside the methods), no steady state to hold
    warmup_frames = 0  # no history: every frame is rendered afresh

    def __init__(self, tracer: Whitted, params: RegularParams):
        self.tracer = tracer
        self._configure(params)

    def _configure(self, params: RegularParams) -> None:
        """Stateless: nothing to keep or reset."""
        self.params = params
        self.spp = params.spp

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        cam = request.camera
        image = np.empty((cam.height, cam.width, 3), dtype=np.float32) if out is None else out
        return self.render_rows(request, stats, 0, cam.height, image)

    def render_rows(
        self, request: FrameRequest, stats: FrameStats, row0: int, rows: int, out: np.ndarray | None = None
    ) -> np.ndarray:
        """Rows row0 to row0 + rows of the image, (rows, width, 3) float32: exactly those rows of render's image,
        as every sample is placed and seeded by its pixel's position in the whole image (a truth renders in
        row blocks across machines, hmdrt.evaluate.cluster)."""
        cam = request.camera
        image = np.empty((rows, cam.width, 3), dtype=np.float32) if out is None else out
        band = max(1, self.tracer.chunk // (cam.width * self.spp))
        for r in range(0, rows, band):
            n = min(band, rows - r)
            with stats.stage("raygen"):
                xy = jittered_pixels(cam.width, row0 + r, n, self.spp, request.seed)
            first = (row0 + r) * cam.width * self.spp
            rgb = self.tracer.trace_samples(cam, xy, sample_keys(first, len(xy), request.seed), stats)
            with stats.stage("resolve"):
                image[r : r + n] = rgb.reshape(n, cam.width, self.spp, 3).mean(axis=2)
        return image
