"""Foveated rendering with gaze-contingent depth of field (weier2018).

Section 3.1: rays are cast where the sampling tables say so: every pixel inside r0, the precomputed
S_in pattern (equation (1), moved with the point of regard) in the transition up to r1, and the static
uniform S_out of density p_min beyond. Temporal anti-aliasing reprojects each traced sample into the
previous frame's pyramid at the level of its footprint (the sample spacing 1 / sqrt(p), which grows
with eccentricity), reads five quincunx taps with their depths, and blends with a running estimate
whose new-sample weight is at least alpha_min and grows as taps fail the depth test. Pull-push
interpolation reconstructs the dense image; its pyramid feeds the next frame and the blur. Section
3.2: the focused depth comes from depth samples around the point of regard and the eyes' vergence;
circles of confusion from the tracking-aware thin lens (equation (3)); the layered near / mid / far
blur (Gaussian in central vision, pyramid in the periphery, blended across the transition); and the
contrast-enhancing combine. Defaults follow section 4.1's benchmark: r0 = 10, r1 = 20, p = 0.2, medium.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import msgspec
import numba as nb
import numpy as np

from hmdrt.foveation.base import HISTORY, Configurable, FrameRequest, Stage, pixel_keys, plan
from hmdrt.foveation.stages.dof import (
    DEPTH_INACCURACY_M,
    DOF_PRESETS,
    MAX_BLUR_PX,
    DofPreset,
    coc_map,
    focal_lengths,
    gaze_depth,
    layered_blur,
)
from hmdrt.foveation.stages.filters import contrast_enhance
from hmdrt.foveation.stages.pyramid import Pyramid, pull_push, quincunx_rgbd
from hmdrt.foveation.stages.reproject import FAR, camera_arrays, project, world_point
from hmdrt.foveation.stages.sampling import Foveal, SamplingTables, pixels_per_degree, sampling_tables, table_mask
from hmdrt.optics.camera import EyeCamera, eccentricity_map
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.gbuffer import GBufferPool
from hmdrt.trace.integrator import Whitted

Deg = Annotated[float, msgspec.Meta(ge=0.0, le=180.0)]
Fraction = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
DOF = "dof"
CONTRAST = "contrast"


class Weier18Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    r0: Deg = 10.0
    r1: Deg = 20.0
    p_min: Fraction = 0.2
    dof: Literal["none", "weak", "medium", "strong"] = "medium"
    pupil_mm: Annotated[float, msgspec.Meta(gt=0.0, le=20.0)] | None = None  # k, overrides the preset's
    retina: Annotated[float, msgspec.Meta(gt=0.0, le=100.0)] | None = None  # E, overrides the preset's
    depth_inaccuracy_m: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = DEPTH_INACCURACY_M  # t
    alpha_min: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.2
    taa_depth: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.05  # relative depth tolerance of a tap
    contrast: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.2
    table_seed: Annotated[int, msgspec.Meta(ge=0, lt=2**31)] = 0

    def __post_init__(self) -> None:
        if self.r0 > self.r1:
            raise ValueError("r0 must not exceed r1")

    def preset(self) -> DofPreset | None:
        base = DOF_PRESETS[self.dof]
        if base is None:
            return None
        return DofPreset(self.pupil_mm or base.pupil_mm, self.retina or base.retina)


@nb.njit(parallel=True, cache=True, nogil=True)
def _taa(pixels, width, cur, prev, depth, rgb, ecc, r0, r1, p_min, pyramid, alpha_min, tol, out):
    """Blend each traced sample with the previous frame's pyramid around its back-projection."""
    data, offsets, widths, heights = pyramid
    pw, ph = widths[0], heights[0]
    for s in nb.prange(pixels.shape[0]):
        i = pixels[s]
        x, y = i % width + 0.5, i // width + 0.5
        px, py, pz = world_point(cur, x, y, depth[s])
        qx, qy, dist = project(prev, px, py, pz)
        if not (qx >= 0.0 and qy >= 0.0 and qx < pw and qy < ph):
            for c in range(3):
                out[s, c] = rgb[s, c]
            continue
        e = ecc[i]
        p = 1.0 if e < r0 else (p_min if e >= r1 else 1.0 - (1.0 - p_min) * (e - r0) / (r1 - r0))
        level = math.log2(max(1.0 / math.sqrt(max(p, 1e-6)), 1.0))
        expected = dist if depth[s] < FAR else math.inf
        valid = 0
        r = g = b = 0.0
        for k in range(5):
            tr, tg, tb, d = quincunx_rgbd(data, offsets, widths, heights, level, qx, qy, k)
            if (math.isinf(expected) and d >= 0.5 * FAR) or abs(d - expected) <= tol * expected:
                valid += 1
                r, g, b = r + tr, g + tg, b + tb
        if valid == 0:
            for c in range(3):
                out[s, c] = rgb[s, c]
            continue
        alpha = max(alpha_min, 1.0 - valid / 5.0)
        out[s, 0] = alpha * rgb[s, 0] + (1.0 - alpha) * r / valid
        out[s, 1] = alpha * rgb[s, 1] + (1.0 - alpha) * g / valid
        out[s, 2] = alpha * rgb[s, 2] + (1.0 - alpha) * b / valid


@dataclass
class _EyeState:
    camera: EyeCamera
    pyramids: list[Pyramid]  # [current, previous]; swapped every frame
    tables: SamplingTables | None = None
    tables_for: tuple | None = None  # the (foveal region, table_seed) the tables were drawn for


class Weier18(Configurable):
    """Table-driven foveated sampling, TAA, pull-push reconstruction and gaze-contingent depth of field."""

    name = "weier18"
    Params = Weier18Params
    stages = (
        Stage("sample"),
        Stage("trace"),
        Stage("taa", frozenset({HISTORY})),
        Stage("ppi"),
        Stage("gaze_depth", frozenset({DOF})),
        Stage("coc", frozenset({DOF})),
        Stage("dof_filter", frozenset({DOF})),
        Stage("combine", frozenset({CONTRAST})),
    )

    def __init__(self, tracer: Whitted, params: Weier18Params):
        self.tracer = tracer
        self._eyes: dict[str, _EyeState] = {}
        self._gbuffers = GBufferPool()
        self._configure(params)

    def _configure(self, params: Weier18Params) -> None:
        """Keeps each eye's reconstruction pyramids, which TAA reprojects. A new foveal region (r0, r1,
        p_min) or table_seed redraws each eye's sampling tables S_in and S_out before its next frame;
        dof, contrast and the TAA settings act on the next frame as they are."""
        self.params = params
        self.foveal = Foveal(params.r0, params.r1, params.p_min)
        self._tables_for = (self.foveal, params.table_seed)
        self.features = frozenset({DOF} if params.preset() else set()) | frozenset(
            {CONTRAST} if params.contrast else set()
        )

    def _state(self, request: FrameRequest) -> tuple[_EyeState, bool]:
        """This eye's state and whether it holds a previous frame of the same size."""
        cam = request.camera
        state = self._eyes.get(request.eye)
        history = state is not None and (state.camera.width, state.camera.height) == (cam.width, cam.height)
        if not history:
            pyramids = [Pyramid.empty(cam.width, cam.height), Pyramid.empty(cam.width, cam.height)]
            state = self._eyes[request.eye] = _EyeState(cam, pyramids)
        if state.tables_for != self._tables_for:
            state.tables = sampling_tables(cam, self.foveal, self.params.table_seed)
            state.tables_for = self._tables_for
        return state, history

    def render(self, request: FrameRequest, stats: FrameStats) -> np.ndarray:
        cam, p = request.camera, self.params
        w, h = cam.width, cam.height
        state, history = self._state(request)
        steps = plan(self.stages, self.features | ({HISTORY} if history else set()))
        with stats.stage("sample"):
            ecc = eccentricity_map(cam, request.gaze)
            por = cam.gaze_pixel(request.gaze)
            pixels = np.flatnonzero(table_mask(ecc, self.foveal, state.tables, por))
            xy = np.empty((len(pixels), 2), np.float32)
            xy[:, 0] = pixels % w + 0.5
            xy[:, 1] = pixels // w + 0.5
        with stats.stage("trace"):
            gbuf = self._gbuffers.rows(len(pixels))
            rgb = self.tracer.trace_samples(cam, xy, pixel_keys(pixels, request.seed, request.frame), stats, gbuf)
        depth = gbuf.primary.depth
        state.pyramids.reverse()
        current, previous = state.pyramids
        if "taa" in steps:
            with stats.stage("taa"):
                smoothed = np.empty_like(rgb)
                _taa(
                    pixels,
                    w,
                    camera_arrays(cam),
                    camera_arrays(state.camera),
                    depth,
                    rgb,
                    ecc.reshape(-1),
                    p.r0,
                    p.r1,
                    p.p_min,
                    tuple(previous),
                    p.alpha_min,
                    p.taa_depth,
                    smoothed,
                )
                rgb = smoothed
        with stats.stage("ppi"):
            current.data.fill(0.0)
            level0 = current.data[: w * h]
            level0[pixels, :3] = rgb
            level0[pixels, 3] = 1.0
            level0[pixels, 4] = np.minimum(depth, FAR)
            pull_push(current)
            base = current.level(0)
            image = np.ascontiguousarray(base[..., :3])
        preset = p.preset()
        if "dof_filter" in steps and preset is not None:
            ppd = sum(pixels_per_degree(cam)) / 2
            with stats.stage("gaze_depth"):
                dense_depth = np.where(base[..., 4] >= 0.5 * FAR, np.inf, base[..., 4])
                focus = gaze_depth(dense_depth, por, ppd, request.gaze_depth_m)
            with stats.stage("coc"):
                coc = coc_map(dense_depth, focus, preset, ppd, p.depth_inaccuracy_m)
            with stats.stage("dof_filter"):
                image = layered_blur(image, coc, ecc, p.r0, p.r1, current)
            stats.metrics["focus_m"] = focus
            # 1 when focus - t fell below the lens's near limit and d_n was kept at 2 d_i (dof.focal_lengths)
            near_mm = focal_lengths(focus, p.depth_inaccuracy_m)[0]
            stats.metrics["focus_near_clamped"] = int(near_mm > focus * 1000.0 - p.depth_inaccuracy_m * 1000.0)
            stats.metrics["coc_max_px"] = float(np.abs(coc).max())
            stats.metrics["coc_capped_pixels"] = int((np.abs(coc) > MAX_BLUR_PX).sum())  # blurred at the cap
        if "combine" in steps:
            with stats.stage("combine"):
                image = contrast_enhance(image, ecc, current, p.contrast, p.r0, p.r1)
        state.camera = cam
        stats.metrics["sample_fraction"] = len(pixels) / (w * h)
        return image
