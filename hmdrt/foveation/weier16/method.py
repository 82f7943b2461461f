"""weier16 (weier2016), the method: each frame reprojects the coarse mesh (section 3.2), marks the resampling info
(section 3.3), selects and traces the samples (section 3.1), updates the cache and merges (section 3.4), and runs the
post filter (section 3.5); each eye's history double-buffered, nothing of the image's size allocated per frame."""

from __future__ import annotations

from typing import Any, NamedTuple

import msgspec
import numpy as np

from hmdrt.foveation.base import HISTORY, STOCHASTIC, Checks, Configurable, FrameRequest, Stage, plan, scene_features
from hmdrt.foveation.registry import register
from hmdrt.foveation.stages.reproject import CoarseMesh, GridProjection, MeshImage
from hmdrt.foveation.stages.sampling import FOVEAL_REGION_KNOBS
from hmdrt.foveation.stages.temporal import AGES, age_table
from hmdrt.foveation.weier16.buffers import (
    CacheRule,
    Final,
    InfoRule,
    PostRule,
    Samples,
    Support,
    Surfaces,
    _Buffers,
)
from hmdrt.foveation.weier16.cache import _gather_support, _unsampled_cells, _update
from hmdrt.foveation.weier16.params import Weier16Params, support_size
from hmdrt.foveation.weier16.post import _post
from hmdrt.foveation.weier16.resample import _resampling_info
from hmdrt.foveation.weier16.selection import _fill_samples, _select
from hmdrt.kernels.schedule import dynamic
from hmdrt.optics.camera import EyeCamera, eccentricity_map
from hmdrt.optics.projection import camera_arrays
from hmdrt.telemetry.stats import FrameStats, nbytes
from hmdrt.trace.gbuffer import GBufferPool, LightBuffer
from hmdrt.trace.integrator import Whitted


class _EyeState:
    """One eye's history: the camera of its newest frame, its final colour and cache info double-buffered
    (the newest is read while the next is written), the newest support image and G-buffer, and the two coarse meshes
    made of it, each eye's own so that a view that holds still rasterises them once (CoarseMesh), both of one
    projection of the support grid (GridProjection)."""

    def __init__(self, w: int, h: int, sw: int, sh: int):
        self.size = (w, h, sw, sh)
        self.camera: EyeCamera | None = None
        self.finals = (Final.empty(w, h), Final.empty(w, h))
        self.newest = 0
        self.support = Support.empty(sw, sh)
        projection = GridProjection(((w, h), (sw, sh)))
        self.mesh = CoarseMesh(projection)  # at full resolution
        self.low_mesh = CoarseMesh(projection)  # at support resolution, for the resampling info


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


@register
class Weier16(Configurable):
    """Foveated ray tracing with coarse-mesh reprojection, resampling info, cache and merge."""

    name = "weier16"
    Params = Weier16Params
    knobs = FOVEAL_REGION_KNOBS
    stages = (
        Stage("reproject", frozenset({HISTORY}), touches=True),
        Stage("resample_info", frozenset({HISTORY})),
        Stage("sample"),
        Stage("trace"),
        Stage("cache_update", touches=True),  # with the reprojected frame's gather and the merge, in one pass
        Stage("post", frozenset({HISTORY, STOCHASTIC})),
    )
    checks = Checks(golden=("whitted", "interior"))  # interior: area lights, the post filter

    @classmethod
    def knob_values(cls, params: Weier16Params) -> dict[str, Any]:
        """The fields, with r0, r1 and p_min as the frc preset resolves them."""
        return msgspec.structs.asdict(params) | params.foveal()._asdict()

    def __init__(self, tracer: Whitted, params: Weier16Params):
        self.tracer = tracer
        self.features = scene_features(tracer)
        self._eyes: dict[str, _EyeState] = {}
        self._buffers: _Buffers | None = None
        self._gbuffers = GBufferPool(("depth", "normal_geometric"), ())  # all it reads of the hits
        self._configure(params)

    def _configure(self, params: Weier16Params) -> None:
        """Keeps each eye's final colour, cache info and support G-buffer: a new foveal region (frc, r0,
        r1, p_min) or new thresholds act on the next frame's samples and cache update, which reprojects
        the cache as usual. A new support size (support_w, support_h) cannot use the previous support
        G-buffer as its coarse mesh, so the next frame starts without history. Draws the resampling info's
        footprint taps (InfoRule.taps) and tabulates k(dt) at whole ages (CacheRule.ages)."""
        foveal = params.foveal()
        self.params, self.foveal = params, foveal
        self._taps = np.random.default_rng(0).standard_normal((params.footprint_samples, 2))
        self._ages = np.empty(AGES)
        age_table(params.k_min, params.k_max, params.t_max, self._ages)

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        f = self._frame(request, out)
        mesh = self._reproject(f, stats)
        resample = self._resample_info(f, stats)
        n, xy, keys, light = self._sample(f, mesh, resample, stats)
        samples, normals = self._trace(f, xy, keys, light, stats)
        written = self._cache_update(f, mesh, samples, normals, stats)
        self._post(f, samples, normals, f.eye.finals[written], stats)
        f.eye.camera, f.eye.newest = f.request.camera, written
        sel = f.buf.selection
        pixels = f.size[0] * f.size[1]
        resampled = int(sel.resampled.sum())
        stats.metrics["sample_fraction"] = n / pixels  # traced pixels, the support image's among them
        stats.metrics["resampled_pixels"] = resampled
        stats.metrics["resampled_fraction"] = resampled / pixels
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
            return f.eye.mesh.image
        w, h = f.size[:2]
        written = w * h * 3 * np.dtype(np.float32).itemsize  # the mesh image: x, y in the previous frame and 1/z
        with stats.stage("reproject", touches=f.eye.support.depth.nbytes + written):
            return f.eye.mesh.reproject(f.eye.camera, f.buf.grid.x, f.buf.grid.y, f.eye.support.depth, f.camera, w, h)

    def _resample_info(self, f: _Frame, stats: FrameStats) -> np.ndarray:
        """Section 3.3: the support cells to sample afresh (the no-history stand-in without a previous frame)."""
        if "resample_info" not in f.steps:
            return f.buf.no_resample
        w, h, sw, sh = f.size
        buf, eye, p = f.buf, f.eye, self.params
        with stats.stage("resample_info"):
            low = eye.low_mesh.reproject(eye.camera, buf.grid.x, buf.grid.y, eye.support.depth, f.camera, sw, sh)
            rule = InfoRule(p.eps_depth, p.eps_lum, p.eps_edge, p.eps_motion, self._taps)
            low_cam, previous = camera_arrays(f.camera, sw, sh), eye.finals[eye.newest]
            _resampling_info(
                low, low_cam, previous.color, eye.support.normal, eye.support.unsampled, eye.camera.position,
                float(w), float(h), rule, buf.low_scratch, buf.resample,
            )  # fmt: skip
            return buf.resample

    def _sample(
        self, f: _Frame, mesh: MeshImage, resample: np.ndarray, stats: FrameStats
    ) -> tuple[int, np.ndarray, np.ndarray, LightBuffer]:
        """Section 3.1: the pixels to trace (foveal probability, resampling info, the support image's pixels),
        and the tracer's sample list, one sample per traced pixel."""
        buf, request, sel = f.buf, f.request, f.buf.selection
        with stats.stage("sample"):
            ecc = eccentricity_map(f.camera, request.gaze)
            zinv = mesh.zinv if f.history else buf.no_zinv
            dynamic(
                _select, ecc, self.foveal, request.seed, request.frame, zinv, resample, buf.grid, sel,
                buf.draws,
            )  # fmt: skip
            np.cumsum(sel.counts, out=sel.row_start[1:])
            n = int(sel.row_start[-1])
            xy, keys, light = buf.sample_list(n)
            key = (request.seed << 32) + request.frame * (1 << 22)
            _fill_samples(sel.flags, sel.row_start, key, xy, keys, buf.sample_index, buf.listed)
            return n, xy, keys, light

    def _trace(
        self, f: _Frame, xy: np.ndarray, keys: np.ndarray, light: LightBuffer, stats: FrameStats
    ) -> tuple[Samples, np.ndarray]:
        """The samples' colour, depth and light buffer, and their geometric normals (n, 3)."""
        w, h = f.size[:2]
        stochastic = STOCHASTIC in self.features
        with stats.stage("trace"):
            gbuf, rgb = self._gbuffers.rows(len(xy), most=w * h)
            self.tracer.trace_samples(f.camera, xy, keys, stats, gbuf, light if stochastic else None, rgb)
        return Samples(rgb, gbuf.primary.depth, light.irradiance, light.albedo), gbuf.primary.normal_geometric

    def _cache_update(
        self, f: _Frame, mesh: MeshImage, samples: Samples, normals: np.ndarray, stats: FrameStats
    ) -> int:
        """Section 3.4: the support image and G-buffer extracted from the support pixels' samples (the next
        frame's coarse mesh), then the reprojected frame's gather, the merge of the new samples and the running
        estimate, in one pass into the final colour and the image; last, the cells that show the support
        image's reconstruction (the next frame's resampling info tests them). Returns which of the eye's final
        buffers it wrote: the other one, or, where the mesh reprojects every pixel onto itself (a still view),
        the previous one in place, whose untraced pixels then keep what they hold instead of being copied."""
        p, t, support, buf = self.params, f.request.frame, f.eye.support, f.buf
        in_place = f.history and f.eye.mesh.still
        written = f.eye.newest if in_place else 1 - f.eye.newest
        previous, final = f.eye.finals[f.eye.newest], f.eye.finals[written]
        stochastic = STOCHASTIC in self.features
        lights = (previous.light, final.light, samples.light) if stochastic else ()
        touched = (buf.selection.flags, *mesh, previous.color, previous.info, final.color, final.info, f.image)
        with stats.stage("cache_update", touches=nbytes(*touched, samples.rgb, samples.depth, *lights)):
            distance = f.eye.mesh.distances() if in_place else buf.no_zinv  # measured once while still
            _gather_support(buf.grid, buf.sample_index, samples, normals, support)
            rule = CacheRule(
                float(t), p.k_min, p.k_max, p.t_max, p.eps_cache, p.footprint_samples, f.request.seed + t, stochastic,
                in_place, self._ages,
            )  # fmt: skip
            dynamic(
                _update, buf.selection, mesh, camera_arrays(f.camera), distance, previous, samples, support, buf.grid,
                rule, buf.taps, final, f.image,
            )  # fmt: skip
            _unsampled_cells(buf.selection.flags, support.unsampled, buf.cell_rows)
        return written

    def _post(self, f: _Frame, samples: Samples, normals: np.ndarray, final: Final, stats: FrameStats) -> None:
        """Section 3.5: the post filter over the stochastic light buffer (of `final`, the frame's), on the image
        shown."""
        p = self.params
        if not (p.post and "post" in f.steps):
            return
        with stats.stage("post"):
            rule = PostRule(
                p.post_radius, p.post_samples, f.request.seed + f.request.frame, p.post_depth, p.post_normal
            )
            surfaces = Surfaces(f.buf.sample_index, samples.depth, normals)
            dynamic(_post, f.buf.selection, surfaces, samples, final, camera_arrays(f.camera), rule, f.image)
