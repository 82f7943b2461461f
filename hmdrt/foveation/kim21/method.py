"""kim21 (kim2021), the method: each frame presamples every pixel centre (section 4.3), reuses pixels of the previous
frame (section 4.4), inspects the subpixels (sections 3 and 4.6.1), supersamples the problematic ones and resolves
(section 4.6.2, Figure 2), and smooths over up to four back-projected earlier frames (section 4.7)."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.base import HISTORY, Checks, Configurable, FrameRequest, Knob, Stage, pixel_keys, plan
from hmdrt.foveation.kim21.bands import Foveation, _foveation, alpha_knots, bezier_controls
from hmdrt.foveation.kim21.disparity import TABLE1, Tests, _inspect
from hmdrt.foveation.kim21.params import Kim21Params
from hmdrt.foveation.kim21.reuse import Kept, _clear, _store
from hmdrt.foveation.kim21.supersample import _exclusive_scan, _resolve, _subpixel_samples
from hmdrt.foveation.registry import register
from hmdrt.foveation.stages.temporal import History, exponential_smoothing, relative_view, same_camera
from hmdrt.kernels.schedule import dynamic
from hmdrt.optics.camera import EyeCamera, eccentricity_map, pixel_grid
from hmdrt.optics.projection import camera_arrays
from hmdrt.telemetry.stats import FrameStats, nbytes
from hmdrt.trace.gbuffer import GBuffer
from hmdrt.trace.integrator import Whitted

MAX_SMOOTH_FRAMES = 4  # section 4.7: up to four earlier frames


class _Buffers(NamedTuple):
    """A frame's G-buffer, presampled colour, reuse counts, classes and drifts, which the next frame's reuse test
    reads (Kept)."""

    gbuffer: GBuffer
    ref: np.ndarray  # (n, 3) float32
    flags: np.ndarray  # (n,) int32
    level: np.ndarray  # (n,) uint8
    drift: np.ndarray  # (n, 2) float32

    @classmethod
    def empty(cls, n: int) -> _Buffers:
        ref, flags = np.empty((n, 3), np.float32), np.zeros(n, np.int32)
        gbuffer = GBuffer.empty(n, TABLE1, TABLE1)  # what the tests and the reuse read; the depth is the history's
        return cls(gbuffer, ref, flags, np.zeros(n, np.uint8), np.zeros((n, 2), np.float32))


class _EyeState:
    """One eye's buffers at one image size, persistent across frames."""

    def __init__(self, height: int, width: int, smooth_size: int):
        n = height * width
        self.shape = (height, width)
        self.history = History(MAX_SMOOTH_FRAMES)  # rendered colour and depth, this frame's in the spare slot
        self.smooth_size = smooth_size  # frames the smoothing history holds since it (re)started
        self.buffers = [_Buffers.empty(n), _Buffers.empty(n)]  # [this frame's, the previous frame's]
        self.previous: EyeCamera | None = None
        self.fov = Foveation.empty(height, width)
        self.fov_key: tuple | None = None
        self.central = 0
        self.most = 0  # extra samples when every subpixel of every central pixel is problematic (_foveation)
        self.sub_mask = np.empty(n, np.uint8)
        self.first = np.empty(height + 1, np.int64)  # per row: the index of its first extra sample
        threads = nb.config.NUMBA_NUM_THREADS
        self.box = np.empty((threads, 6, width + 2))  # the inspection's 3x3 contrast boxes (_box_contrast_row)
        self.passes = np.empty((threads, width), np.bool_)
        self.extra_xy = np.empty((0, 2), np.float32)
        self.extra_keys = np.empty(0, np.int64)
        self.extra_color = np.empty((0, 3), np.float32)

    def extra(self, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """xy, keys and colour for `count` extra samples; when too small, grown to the most the foveation can ask
        for, so that the count's changes from frame to frame (reuse, the view) do not allocate (np.empty: the pages
        no frame fills stay untouched)."""
        if len(self.extra_keys) < count:
            size = max(count, self.most)
            self.extra_xy, self.extra_keys = np.empty((size, 2), np.float32), np.empty(size, np.int64)
            self.extra_color = np.empty((size, 3), np.float32)
        return self.extra_xy[:count], self.extra_keys[:count], self.extra_color[:count]


def _kept(buffers: _Buffers, history: History, slot: int) -> Kept:
    """A frame's Kept: its buffers, with the depth and colour of its history slot."""
    n = len(buffers.flags)
    depth, color = history.depth[slot].reshape(n), history.color[slot].reshape(n, 3)
    return Kept(buffers.ref, depth, buffers.flags, color, buffers.level, buffers.drift)


class _Frame(NamedTuple):
    """What the stages of one frame share: its request, the eye's state and foveation, this frame's and the
    previous frame's buffers, the history slot it is written to and both frames' kept colours, and its plan."""

    request: FrameRequest
    state: _EyeState
    fov: Foveation
    cur: _Buffers
    last: _Buffers
    slot: int
    kept: Kept
    prev: Kept
    steps: tuple[str, ...]

    @property
    def camera(self) -> EyeCamera:
        return self.request.camera


@register
class Kim21(Configurable):
    """Selective foveated supersampling, reuse and smoothing on top of Whitted presampling."""

    name = "kim21"
    Params = Kim21Params
    # the samples per problematic subpixel down to 1 (section 4.6.2); the band edges move only with the foveal
    # widening (shrinking them changes tau_fov's shape, which may not hold)
    knobs = (
        *(Knob(f"n_{band}", 1) for band in ("f", "p", "m", "np")),
        *(Knob(f"e_{band}", None, foveal=True) for band in ("f", "p", "m", "np", "max")),
    )
    stages = (
        Stage("presample"),
        Stage("reuse", frozenset({HISTORY})),
        Stage("inspect"),
        Stage("supersample"),
        Stage("resolve"),
        Stage("smooth", frozenset({HISTORY}), touches=True),
    )
    checks = Checks(golden=("whitted", "interior"))  # interior: area lights and ambient occlusion

    def __init__(self, tracer: Whitted, params: Kim21Params):
        self.tracer = tracer
        self._eyes: dict[str, _EyeState] = {}
        self._keys = np.empty(0, np.int64)
        self._keys_seed: int | None = None
        self._configure(params)

    @property
    def warmup_frames(self) -> int:
        """The earlier frames temporal smoothing blends (section 4.7), and one for pixel reuse (section 4.4); none
        for Jin et al.'s selective supersampling (neither)."""
        p = self.params
        return max(p.smooth_frames if p.smooth else 0, 1 if p.reuse else 0)

    def _configure(self, params: Kim21Params) -> None:
        """Keeps each eye's previous frame (pixel reuse goes on, its reuse counts included) and its
        smoothing history; new bands, sample counts and thresholds act on the next frame. Only a larger
        smooth_frames than an eye's history holds starts that history afresh (see render)."""
        p = params
        self.ctrl = bezier_controls(p)
        self.tests = Tests(
            np.array(
                [p.tau_col, p.tau_poid, p.tau_psn, p.tau_psc, p.tau_pte, p.tau_soid, p.tau_ssn, p.tau_ssc, p.tau_ste]
            ),
            p.normal_cos,
            p.tau_reuse,
            p.n_reuse_max,
            p.depth_tolerance,
            p.reuse_px,
        )
        self.bounds = np.array([p.e_f, p.e_p, p.e_m])
        self.counts = np.array([p.n_f, p.n_p, p.n_m, p.n_np], np.uint8)
        self.alpha = (alpha_knots(p), np.array(p.alpha))
        self.params = params

    def _state(self, eye: str, height: int, width: int) -> _EyeState:
        """The eye's buffers; a new image size starts them afresh, the smoothing history's size kept."""
        frames = max(self.params.smooth_frames, 1)
        state = self._eyes.get(eye)
        if state is None or state.shape != (height, width):
            state = self._eyes[eye] = _EyeState(height, width, frames if state is None else state.smooth_size)
        if state.smooth_size < frames:
            state.smooth_size = frames
            state.history.restart()
        return state

    def _foveation(self, state: _EyeState, cam: EyeCamera, gaze: np.ndarray) -> Foveation:
        """The eye's Foveation, recomputed when the frustum, the gaze or the parameters changed."""
        key = (cam.tan_left, cam.tan_right, cam.tan_up, cam.tan_down, float(gaze[0]), float(gaze[1]), float(gaze[2]))
        if state.fov_key is None or state.fov_key[0] != key or state.fov_key[1] is not self.params:
            ecc = eccentricity_map(cam, gaze)
            state.central, state.most = _foveation(
                ecc, self.ctrl, self.bounds, self.counts, self.params.e_np, *self.alpha, state.fov
            )
            state.fov_key = (key, self.params)
        return state.fov

    def _pixel_keys(self, n: int, seed: int) -> np.ndarray:
        """pixel_keys of pixels 0..n-1, kept while n and the seed stay."""
        if len(self._keys) != n or self._keys_seed != seed:
            self._keys, self._keys_seed = pixel_keys(np.arange(n), seed), seed
        return self._keys

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        f = self._frame(request, stats)
        self._presample(f, stats)
        reused = self._reuse(f, stats)
        problematic, extra_xy, extra_keys, extra_color = self._inspect_subpixels(f, stats)
        with stats.stage("supersample"):
            extra = self.tracer.trace_samples(f.camera, extra_xy, extra_keys, stats, out=extra_color)
        self._resolve_pixels(f, extra, stats)
        image = self._smooth(f, out, stats)
        f.state.history.commit(f.camera)
        f.state.previous = f.camera
        n = f.state.shape[0] * f.state.shape[1]
        stats.metrics["central_pixels"] = f.state.central
        stats.metrics["reused_pixels"] = reused
        stats.metrics["reuse_fraction"] = reused / f.state.central if f.state.central else 0.0  # Figure 6's share
        stats.metrics["problematic_subpixels"] = problematic
        stats.metrics["extra_samples"] = len(extra)
        stats.metrics["sample_fraction"] = (n + len(extra)) / n
        return image

    def _frame(self, request: FrameRequest, stats: FrameStats) -> _Frame:
        """The eye's state and this frame's foveation, buffers (this frame's and the previous one's) and history
        slot, with the plan of its stages."""
        cam = request.camera
        h, w = cam.height, cam.width
        state = self._state(request.eye, h, w)
        steps = plan(self.stages, frozenset({HISTORY}) if state.previous is not None else frozenset())
        with stats.stage("eccentricity"):
            fov = self._foveation(state, cam, request.gaze)
        state.buffers.reverse()
        cur, last = state.buffers
        history = state.history
        slot, newest = history.begin((h, w)), max(history.newest((h, w)), 0)
        kept, prev = _kept(cur, history, slot), _kept(last, history, newest)
        return _Frame(request, state, fov, cur, last, slot, kept, prev, steps)

    def _presample(self, f: _Frame, stats: FrameStats) -> None:
        """Section 4.3: one sample at every pixel centre, with the G-buffer (Table 1) the inspection reads; the
        colour and the hit distance go straight into the frame's history slot (its kept rendered colour and depth)."""
        h, w = f.state.shape
        with stats.stage("presample"):
            _clear(w, f.cur.gbuffer.secondary, f.fov.spans)
            keys = self._pixel_keys(h * w, f.request.seed)
            primary, secondary = f.cur.gbuffer.primary, f.cur.gbuffer.secondary
            gbuffer = GBuffer(primary._replace(depth=f.kept.depth), secondary, f.fov.table1)
            self.tracer.trace_samples(f.camera, pixel_grid(w, h), keys, stats, gbuffer, out=f.kept.rendered)

    def _reuse(self, f: _Frame, stats: FrameStats) -> int:
        """Section 4.4: each pixel's presample stored, its supersampled colour reused from the previous frame where
        the back-projection finds the same surface; returns how many pixels reused theirs."""
        cam, state = f.camera, f.state
        reuse = self.params.reuse and "reuse" in f.steps
        with stats.stage("reuse" if reuse else "store"):
            return dynamic(
                _store,
                state.shape[1],
                f.cur.gbuffer.primary,
                f.cur.gbuffer.secondary,
                camera_arrays(cam).frustum,
                f.kept,
                relative_view(state.previous or cam, cam),
                f.last.gbuffer.primary,
                f.last.gbuffer.secondary,
                f.prev,
                same_camera(state.previous, cam),
                self.tests,
                reuse,
                f.fov,
            )

    def _inspect_subpixels(self, f: _Frame, stats: FrameStats) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
        """Sections 3 and 4.6: the disparity test per subpixel, then the extra samples of the problematic ones
        (xy, keys and a colour buffer), after how many subpixels were problematic. Their jitter and keys are drawn
        afresh each frame (pixel_keys' frame), so that smoothing (section 4.7) averages them on a still view."""
        state, (h, w) = f.state, f.state.shape
        with stats.stage("inspect"):
            g1, g2 = f.cur.gbuffer.primary, f.cur.gbuffer.secondary
            scratch = (state.sub_mask, state.first, state.box, state.passes)
            problematic = _inspect(w, f.cur.ref, g1, g2, f.fov, f.cur.flags, self.tests, *scratch)
            state.first[h] = 0
            total = _exclusive_scan(state.first)
            extra_xy, extra_keys, extra_color = state.extra(total)
            seed_key = int(pixel_keys(np.zeros(1), f.request.seed, f.request.frame, stream=1)[0])
            fov = f.fov
            _subpixel_samples(w, state.sub_mask, fov.samples, fov.spans, state.first, seed_key, extra_xy, extra_keys)
        return problematic, extra_xy, extra_keys, extra_color

    def _resolve_pixels(self, f: _Frame, extra: np.ndarray, stats: FrameStats) -> None:
        """Section 4.6.2 and Figure 2: the rendered pixels' colours from their subpixels (_resolve)."""
        state, (h, w) = f.state, f.state.shape
        with stats.stage("resolve"):
            image, flags, interpolate = f.cur.ref.reshape(h, w, 3), f.cur.flags, self.params.interpolate
            subpixels = (state.sub_mask, f.fov.samples, f.fov.spans, flags, state.first, extra, interpolate)
            dynamic(_resolve, image, *subpixels, f.kept.rendered)

    def _smooth(self, f: _Frame, out: np.ndarray | None, stats: FrameStats) -> np.ndarray:
        """Section 4.7: exponential smoothing over the history by eccentricity, an earlier frame that sees another
        surface left out of both sums (its null colour); the frame as resolved without it."""
        p, history, (h, w) = self.params, f.state.history, f.state.shape
        image = np.empty((h, w, 3), np.float32) if out is None else out
        if not (p.smooth and p.smooth_frames and "smooth" in f.steps):
            image[:] = history.color[f.slot]
            return image
        alpha = f.fov.alpha.reshape(h, w)
        depth, color = history.depth[f.slot], history.color[f.slot]
        earlier = min(p.smooth_frames, len(history.order((h, w))))  # each read once, as the frame itself
        with stats.stage("smooth", touches=nbytes(alpha, image) + (1 + earlier) * nbytes(depth, color)):
            exponential_smoothing(f.camera, depth, color, alpha, history, p.smooth_frames, p.depth_tolerance, image)
        return image
