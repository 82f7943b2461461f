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
from dataclasses import dataclass, field
from typing import Annotated, Literal, NamedTuple

import msgspec
import numba as nb
import numpy as np

from hmdrt.foveation.base import HISTORY, Checks, Configurable, FrameRequest, Stage, plan
from hmdrt.foveation.registry import register
from hmdrt.foveation.stages.dof import (
    DEPTH_INACCURACY_M,
    DOF_PRESETS,
    Blur,
    DofPreset,
    Layers,
    combine,
    focal_lengths,
    gaze_depth,
    horizontal_pass,
    lens,
)
from hmdrt.foveation.stages.filters import FINE_LEVELS, Contrast, contrast_levels, enhance_windows, prefilter
from hmdrt.foveation.stages.pyramid import (
    DEPTH,
    Columns,
    LevelSamples,
    PixelAxes,
    Pyramid,
    RowSamples,
    level_runs,
    pixel_axes,
    pull_push,
    push_columns,
    quincunx,
)
from hmdrt.foveation.stages.sampling import (
    FOVEAL_REGION_KNOBS,
    Density,
    Foveal,
    SampleSet,
    SamplingTables,
    pixels_per_degree,
    sampling_tables,
)
from hmdrt.foveation.stages.temporal import ray_point, relative_view, view_project
from hmdrt.kernels.jit import kernel, serial
from hmdrt.kernels.schedule import claim, dynamic
from hmdrt.optics.camera import EyeCamera, eccentricity_map
from hmdrt.optics.projection import FAR, camera_arrays, pixel_tangents
from hmdrt.ranges import Deg, Fraction
from hmdrt.telemetry.stats import FrameStats, nbytes
from hmdrt.trace.gbuffer import GBufferPool
from hmdrt.trace.integrator import Whitted

DOF = "dof"
BLOCK = 1024  # samples per call of the TAA's serial block function


class Weier18Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    r0: Deg = 10.0
    r1: Deg = 20.0
    p_min: Fraction = 0.2
    density: Density = "printed"  # equation (1) as printed, or "linear" with the polar Jacobian
    dof: Literal["none", "weak", "medium", "strong"] = "medium"
    pupil_mm: Annotated[float, msgspec.Meta(gt=0.0, le=20.0)] | None = None  # k, overrides the preset's
    retina: Annotated[float, msgspec.Meta(gt=0.0, le=100.0)] | None = None  # E, overrides the preset's
    depth_inaccuracy_m: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = DEPTH_INACCURACY_M  # t
    alpha_min: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.2
    taa_depth: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.05  # relative depth tolerance of a tap
    contrast: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.2
    table_seed: Annotated[int, msgspec.Meta(ge=0, lt=2**31)] = 0
    # section 4.1's "full" mode: every pixel sampled and no TAA, with the same CoC, filter and combine
    mode: Literal["foveated", "full"] = "foveated"

    def __post_init__(self) -> None:
        if self.r0 > self.r1:
            raise ValueError("r0 must not exceed r1")

    def preset(self) -> DofPreset | None:
        base = DOF_PRESETS[self.dof]
        if base is None:
            return None
        return DofPreset(self.pupil_mm or base.pupil_mm, self.retina or base.retina)


class Traced(NamedTuple):
    """A frame's traced samples: row-major pixel and its centre, footprint level and its quincunx offset, hit
    distance (inf: miss), radiance; after TAA (_taa) the distance capped at FAR and the radiance blended, as level 0
    of the frame's pyramid holds them."""

    pixels: np.ndarray  # (n,) int64
    xy: np.ndarray  # (n, 2) float32
    level: np.ndarray  # (n,) float64
    offset: np.ndarray  # (n,) float64
    depth: np.ndarray  # (n,) float32
    rgb: np.ndarray  # (n, 3) float32


class Blend(NamedTuple):
    """TAA's blend settings."""

    alpha_min: float
    tol: float  # relative depth tolerance of a tap


class Reprojected(NamedTuple):
    """TAA's scratch for a block of samples, one row per numba thread (nb.get_thread_id()): each sample's pixel
    coordinates in the previous frame, the distance a tap must show to see its surface (inf: a miss) and the
    pyramid level its taps read (-1: none, the sample falls outside the previous frame)."""

    x: np.ndarray  # (threads, BLOCK) float64
    y: np.ndarray
    expected: np.ndarray
    level: np.ndarray
    runs: np.ndarray  # (threads, BLOCK + 1, 2) int64: the block's runs of samples on one level (pyramid.level_runs)

    @classmethod
    def empty(cls) -> Reprojected:
        threads = nb.config.NUMBA_NUM_THREADS
        shape = (threads, BLOCK)
        runs = np.zeros((threads, BLOCK + 1, 2), np.int64)
        return cls(np.zeros(shape), np.zeros(shape), np.zeros(shape), np.zeros(shape), runs)


class Tangents(NamedTuple):
    """The view rays' tangents through the centres of an image's pixel columns and rows (projection.pixel_tangents
    depends on x and y apart): a sample at a pixel centre looks them up, where each would take a division."""

    x: np.ndarray  # (width,) float64
    y: np.ndarray  # (height,) float64

    @classmethod
    def of(cls, camera: EyeCamera) -> Tangents:
        out = cls(np.empty(camera.width), np.empty(camera.height))
        _tangent_tables(camera_arrays(camera).frustum, out)
        return out


@serial
def _tangent_tables(frustum, out):
    """The Tangents of the camera with this frustum (CameraArrays.frustum) into `out`, of its size."""
    for i in range(out.x.shape[0]):
        out.x[i] = pixel_tangents(frustum, i + 0.5, 0.5)[0]
    for j in range(out.y.shape[0]):
        out.y[j] = pixel_tangents(frustum, 0.5, j + 0.5)[1]


@serial
def _tap(tap, expected, tol, valid, r, g, b):
    """Adds quincunx tap `tap` (colour and depth, pyramid.quincunx) to the count and the colour sums if it sees the
    sample's surface (its depth within tol of the expected one, or both misses)."""
    d = tap[3]
    if (d >= 0.5 * FAR) if math.isinf(expected) else abs(d - expected) <= tol * expected:
        return valid + 1, r + tap[0], g + tap[1], b + tap[2]
    return valid, r, g, b


@serial
def _taa_block(traced, tangents, view, blend, previous, history, start, stop, where):
    """Samples [start, stop): with history, each one's point in the current eye frame (along its pixel centre's ray,
    Tangents) seen from the previous frame (its relative_view `view`) into `where`, in a loop of selects that
    vectorises, then the previous pyramid's quincunx taps there blended into its rgb, in one pass per level the block
    reads, over its runs of samples on that level (as pyramid.sample_row: a pass's level constants stay put, where a
    loop that picks each sample's level reloads them); a sample on a whole level reads that level alone. Last, each
    sample's depth capped at FAR: what level 0 is to hold, which the pull-push writes there (pyramid.LevelSamples)."""
    _, xy, levels, offsets, depth, rgb = traced
    alpha_min, tol = blend
    p_data, p_offsets, p_widths, p_heights, p_sx, p_sy = previous
    at_x, at_y, expected, at_level, runs = where
    top = len(p_offsets) - 1
    pw, ph = p_widths[0], p_heights[0]
    if history:
        ftop = float(top)
        tan_x, tan_y = tangents
        block_xy, block_depth, block_levels = xy[start:stop], depth[start:stop], levels[start:stop]
        for j in range(stop - start):  # the rays' tangents, table lookups that would keep the next loop scalar
            at_x[j], at_y[j] = tan_x[np.uint64(block_xy[j, 0])], tan_y[np.uint64(block_xy[j, 1])]
        for j in range(stop - start):  # indices from 0: no negative-index selects, so the loop vectorises
            px, py, pz = ray_point(at_x[j], at_y[j], block_depth[j])
            qx, qy, dist = view_project(view, px, py, pz)
            at_x[j], at_y[j] = qx, qy
            expected[j] = dist if block_depth[j] < FAR else math.inf
            inside = (qx >= 0.0) & (qy >= 0.0) & (qx < pw) & (qy < ph)
            at_level[j] = min(max(block_levels[j], 0.0), ftop) if inside else -1.0
        count, lo, hi = level_runs(at_level, stop - start, top, runs)
        for k in range(lo, hi + 1):
            up = min(k + 1, top)
            lower = (p_offsets[k], p_widths[k], p_heights[k], p_sx[k], p_sy[k])
            upper = (p_offsets[up], p_widths[up], p_heights[up], p_sx[up], p_sy[up])
            for run in range(count):
                if runs[run, 1] != k:
                    continue
                for j in range(runs[run, 0], runs[run + 1, 0]):
                    s, level = start + j, at_level[j]
                    qx, qy, off, e = at_x[j], at_y[j], offsets[s], expected[j]
                    t = level - k  # 0 on the top level and on whole levels, where the next level adds nothing
                    taps = quincunx(p_data, lower, upper, t, off, qx, qy)
                    valid, tr, tg, tb = _tap(taps[0], e, tol, 0, 0.0, 0.0, 0.0)
                    valid, tr, tg, tb = _tap(taps[1], e, tol, valid, tr, tg, tb)
                    valid, tr, tg, tb = _tap(taps[2], e, tol, valid, tr, tg, tb)
                    valid, tr, tg, tb = _tap(taps[3], e, tol, valid, tr, tg, tb)
                    valid, tr, tg, tb = _tap(taps[4], e, tol, valid, tr, tg, tb)
                    if valid > 0:
                        alpha = max(alpha_min, 1.0 - valid / 5.0)
                        rgb[s, 0] = alpha * rgb[s, 0] + (1.0 - alpha) * tr / valid
                        rgb[s, 1] = alpha * rgb[s, 1] + (1.0 - alpha) * tg / valid
                        rgb[s, 2] = alpha * rgb[s, 2] + (1.0 - alpha) * tb / valid
    for s in range(start, stop):
        depth[s] = min(depth[s], FAR)


@kernel
def _taa_blocks(traced, tangents, view, blend, previous, history, where, counter, threads):
    """_taa's blocks, claimed (hmdrt.kernels.schedule): a foveal sample taps one level, a peripheral one two, one
    outside the previous frame none."""
    n = traced.pixels.shape[0]
    blocks = (n + BLOCK - 1) // BLOCK
    for _ in nb.prange(threads):
        t = nb.get_thread_id()
        rows = Reprojected(where.x[t], where.y[t], where.expected[t], where.level[t], where.runs[t])
        block = claim(counter)
        while block < blocks:
            start, stop = block * BLOCK, min(n, (block + 1) * BLOCK)
            _taa_block(traced, tangents, view, blend, previous, history, start, stop, rows)
            block = claim(counter)


def _taa(
    traced: Traced,
    tangents: Tangents,
    view: np.ndarray,
    blend: Blend,
    previous: Pyramid,
    history: bool,
    where: Reprojected,
) -> None:
    """Each traced sample's colour blended with the previous frame's pyramid around its back-projection
    (temporal.relative_view `view` of the previous camera; `tangents`: the current camera's) when there is history,
    and its depth capped at FAR, in place: what level 0 is to hold (pull_push writes them there); `where`:
    Reprojected scratch."""
    dynamic(_taa_blocks, traced, tangents, view, blend, previous, history, where)


@dataclass
class _EyeState:
    camera: EyeCamera
    pyramids: list[Pyramid]  # [current, previous]; swapped every frame
    axes: PixelAxes  # the pyramids' pixel_axes (theirs is the image's size)
    columns: Columns  # pull-push's scratch (push_columns)
    rows: RowSamples  # the combine's scratch
    reprojected: Reprojected = field(default_factory=Reprojected.empty)  # TAA's scratch
    tables: SamplingTables | None = None
    tables_for: tuple | None = None  # the (foveal region, table_seed, density) the tables were drawn for
    samples: SampleSet = field(default_factory=SampleSet)
    keys: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # the samples' random-stream keys
    levels: np.ndarray | None = None  # contrast enhancement's blur level per pixel
    spans: np.ndarray | None = None  # enhance_windows' scratch
    windows: np.ndarray | None = None  # the texels of each level the enhancement reads (enhance_windows)
    blurred: Pyramid | None = None  # contrast enhancement's prefiltered pyramid
    levels_for: tuple | None = None  # the (gaze, r0, r1) the levels and windows were computed for
    tangents: Tangents | None = None  # TAA's view rays through the pixel centres
    tangents_for: tuple | None = None  # the frustum they were computed for
    layers: Layers | None = None  # the depth of field's buffers


@register
class Weier18(Configurable):
    """Table-driven foveated sampling, TAA, pull-push reconstruction and gaze-contingent depth of field."""

    name = "weier18"
    Params = Weier18Params
    knobs = FOVEAL_REGION_KNOBS
    stages = (
        Stage("sample"),
        Stage("trace"),
        Stage("taa", frozenset({HISTORY}), touches=True),
        Stage("ppi", touches=True),
        Stage("gaze_depth", frozenset({DOF})),
        Stage("coc", frozenset({DOF}), touches=True),
        Stage("dof_filter", frozenset({DOF}), touches=True),
        Stage("combine", touches=True),
    )
    checks = Checks(golden=("whitted",), variants=("", "dof=none"))  # and without depth of field

    def __init__(self, tracer: Whitted, params: Weier18Params):
        self.tracer = tracer
        self._eyes: dict[str, _EyeState] = {}
        self._gbuffers = GBufferPool(("depth",), ())  # the primary hits' depth is all it reads
        self._configure(params)

    def _configure(self, params: Weier18Params) -> None:
        """Keeps each eye's reconstruction pyramids, which TAA reprojects. A new foveal region (r0, r1,
        p_min), table_seed or density redraws each eye's sampling tables S_in and S_out before its next frame;
        dof, contrast and the TAA settings act on the next frame as they are."""
        self.params = params
        self.foveal = Foveal(params.r0, params.r1, params.p_min)
        self._tables_for = (self.foveal, params.table_seed, params.density)
        self.features = frozenset({DOF} if params.preset() else set())

    @property
    def warmup_frames(self) -> int:
        """TAA's history (section 3.1): the frames until the first one weighs under 5% of the running estimate;
        none in full mode, which keeps no history."""
        a = self.params.alpha_min
        if self.params.mode == "full":
            return 0
        return 1 if a >= 1.0 else math.ceil(math.log(0.05) / math.log1p(-a))

    def _state(self, request: FrameRequest) -> tuple[_EyeState, bool]:
        """This eye's state and whether it holds a previous frame of the same size."""
        cam = request.camera
        state = self._eyes.get(request.eye)
        history = state is not None and (state.camera.width, state.camera.height) == (cam.width, cam.height)
        if not history:
            pyramids = [Pyramid.empty(cam.width, cam.height), Pyramid.empty(cam.width, cam.height)]
            axes, columns, rows = pixel_axes(pyramids[0]), push_columns(cam.width), RowSamples.empty(cam.width)
            state = self._eyes[request.eye] = _EyeState(cam, pyramids, axes, columns, rows)
        if state.tables_for != self._tables_for and self.params.mode == "foveated":
            state.tables = sampling_tables(cam, self.foveal, self.params.table_seed, self.params.density)
            state.tables_for = self._tables_for
        return state, history

    def _select(self, state: _EyeState, request: FrameRequest) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The eccentricity map and point of regard; the samples, their keys and the contrast levels for them,
        recomputed only when the gaze, the frustum or the tables change."""
        cam, gaze = request.camera, request.gaze
        ecc = eccentricity_map(cam, gaze)
        por = cam.gaze_pixel(gaze)
        view = (cam._frustum(), float(gaze[0]), float(gaze[1]), float(gaze[2]))
        if self.params.mode == "full":
            state.samples.update_all(ecc)
        else:
            state.samples.update((view, state.tables_for), cam, gaze, ecc, self.foveal, state.tables)
        p = self.params
        if state.levels_for != (view, p.r0, p.r1):
            if state.levels is None or state.levels.shape[:2] != ecc.shape:
                state.levels = np.empty(ecc.shape, np.float32)
                state.spans = np.empty((ecc.shape[0], FINE_LEVELS, 2), np.int64)
            contrast_levels(ecc, p.r0, state.levels)
            contrast = Contrast(p.contrast, p.r0, p.r1, state.levels)
            state.windows = enhance_windows(ecc, contrast, state.pyramids[0], state.spans)
            state.levels_for = (view, p.r0, p.r1)
        n = state.samples.count
        if len(state.keys) < n:
            state.keys = np.empty(request.camera.width * request.camera.height, np.int64)  # the bound, once
        # base.pixel_keys(pixels, seed, frame) without its temporary
        offset = (np.int64(request.seed) << np.int64(32)) + np.int64(request.frame) * np.int64(1 << 22)
        keys = np.add(state.samples.pixels, offset, out=state.keys[:n])
        return ecc, por, keys

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        state, history = self._state(request)
        keeps_history = history and self.params.mode == "foveated"
        steps = plan(self.stages, self.features | ({HISTORY} if keeps_history else set()))
        with stats.stage("sample"):
            ecc, por, keys = self._select(state, request)
        traced = self._trace(state, request, keys, stats)
        current = self._reconstruct(state, request.camera, traced, steps, stats)
        layers, blur = self._depth_of_field(state, request, current, ecc, por, steps, stats)
        cam, p = request.camera, self.params
        if out is None:
            out = np.empty((cam.height, cam.width, 3), np.float32)
        base = current.level(0)  # the colour is read from it with the other channels around it
        touches = nbytes(base, ecc, out)
        if p.contrast:  # the prefilter's windows read and written, the contrast's levels
            windows = state.windows
            texels = int(((windows[:, 1] - windows[:, 0]) * (windows[:, 3] - windows[:, 2])).sum())
            touches += 2 * texels * current.data.itemsize * current.data.shape[1] + state.levels.nbytes
        if layers is not None:
            touches += nbytes(layers.coc, layers.far, layers.near)
        with stats.stage("combine", touches=touches):
            blurred = current  # read only with contrast on
            if p.contrast:
                if state.blurred is None or state.blurred.data.shape != current.data.shape:
                    state.blurred = Pyramid.empty(cam.width, cam.height)
                blurred = prefilter(current, state.blurred, state.windows)
            contrast = Contrast(p.contrast, p.r0, p.r1, state.levels)
            combine(base, ecc, layers, blur, current, contrast, blurred, state.axes, state.rows, out)
        state.camera = request.camera
        stats.metrics["sample_fraction"] = state.samples.count / (cam.width * cam.height)
        return out

    def _trace(self, state: _EyeState, request: FrameRequest, keys: np.ndarray, stats: FrameStats) -> Traced:
        samples = state.samples
        with stats.stage("trace"):
            cam = request.camera
            gbuf, rgb = self._gbuffers.rows(samples.count, most=cam.width * cam.height)
            self.tracer.trace_samples(request.camera, samples.xy, keys, stats, gbuf, out=rgb)
        return Traced(samples.pixels, samples.xy, samples.level, samples.offset, gbuf.primary.depth, rgb)

    @staticmethod
    def _tangents(state: _EyeState, cam: EyeCamera) -> Tangents:
        """The camera's Tangents, computed again only when its frustum changes."""
        if state.tangents_for != cam._frustum():
            state.tangents, state.tangents_for = Tangents.of(cam), cam._frustum()
        return state.tangents

    def _reconstruct(
        self, state: _EyeState, cam: EyeCamera, traced: Traced, steps: tuple[str, ...], stats: FrameStats
    ) -> Pyramid:
        """Section 3.1: the samples blended into the reprojected previous frame (TAA), then pull-push fills the
        pixels no sample reached (PPI); returns this frame's pyramid."""
        p = self.params
        state.pyramids.reverse()
        current, previous = state.pyramids
        tangents, view = self._tangents(state, cam), relative_view(state.camera, cam)
        blend = Blend(p.alpha_min, p.taa_depth)
        texel = current.data.itemsize * current.data.shape[1]
        samples = LevelSamples(
            state.samples.mask.reshape(-1), traced.pixels, state.samples.starts, traced.rgb, traced.depth
        )
        if "taa" in steps:  # each sample read and written back, and at least one texel of the previous frame read
            with stats.stage("taa", touches=nbytes(*traced, samples.rgb, samples.depth) + len(traced.pixels) * texel):
                _taa(traced, tangents, view, blend, previous, True, state.reprojected)
        # level 0 written by the push (its samples too), the coarser levels by the pull and read by the push, the
        # samples read twice
        fine = current.level(0).nbytes
        with stats.stage("ppi", touches=fine + 2 * (current.data.nbytes - fine) + 2 * nbytes(*samples)):
            if "taa" not in steps:
                _taa(traced, tangents, view, blend, previous, False, state.reprojected)
            pull_push(current, samples, state.columns)
        return current

    def _depth_of_field(
        self,
        state: _EyeState,
        request: FrameRequest,
        current: Pyramid,
        ecc: np.ndarray,
        por: np.ndarray,
        steps: tuple[str, ...],
        stats: FrameStats,
    ) -> tuple[Layers | None, Blur]:
        """Section 3.2: the focus at the gaze, the circles of confusion and the first (horizontal) pass of the
        layered blur; no layers when the preset is none."""
        p, cam = self.params, request.camera
        preset, blur = p.preset(), Blur(p.r0, p.r1)
        if "dof_filter" not in steps or preset is None:
            return None, blur
        base = current.level(0)
        ppd = sum(pixels_per_degree(cam)) / 2
        with stats.stage("gaze_depth"):
            focus = gaze_depth(base[..., DEPTH], por, ppd, request.gaze_depth_m, miss=0.5 * FAR)
        if state.layers is None or state.layers.coc.shape != (cam.height, cam.width):
            state.layers = Layers.empty(cam.width, cam.height)
        layers = state.layers
        with stats.stage("coc", touches=nbytes(base, layers.coc)):
            layers.compute_coc(base, lens(focus, preset, ppd, p.depth_inaccuracy_m), miss=0.5 * FAR)
        with stats.stage("dof_filter", touches=nbytes(base, ecc, layers.coc, layers.far, layers.near)):
            blur = blur._replace(radius=layers.near_radius())
            horizontal_pass(base, ecc, layers, blur)
        stats.metrics["focus_m"] = focus
        # 1 when focus - t fell below the lens's near limit and d_n was kept at 2 d_i (dof.focal_lengths)
        near_mm = focal_lengths(focus, p.depth_inaccuracy_m)[0]
        stats.metrics["focus_near_clamped"] = int(near_mm > focus * 1000.0 - p.depth_inaccuracy_m * 1000.0)
        coc_max, capped = layers.coc_figures()
        stats.metrics["coc_max_px"] = coc_max
        stats.metrics["coc_capped_pixels"] = capped  # blurred at the cap
        return layers, blur
