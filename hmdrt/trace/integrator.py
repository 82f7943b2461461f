"""Whitted ray tracing of arbitrary camera samples (default depth 3): the entry point every method uses.

Every foveation method hands this its sample positions; nothing else casts or shades rays. The work is
one fused kernel (hmdrt.trace.wavefront) on the tracer's threads, over scratch that persists across
calls, so a frame allocates nothing but what the caller asks for (the radiance, unless it passes `out`).
Stages a scene cannot use are not run (no point lights -> no "shadow", no mirrors or glass -> no "secondary").
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager

import numpy as np

from hmdrt.kernels.memory import retain_freed_memory
from hmdrt.optics.camera import EyeCamera
from hmdrt.scene.model import Scene
from hmdrt.scene.pack import pack
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace import compile_aside, meter
from hmdrt.trace.gbuffer import GBuffer, LightBuffer
from hmdrt.trace.lighting import light_plan
from hmdrt.trace.tracer import Tracer
from hmdrt.trace.wavefront import Frame, Lane, SceneArgs, compile_part, lane_empty, trace

RAYS_PER_CHUNK = 1 << 20  # callers that build sample arrays in bands keep a band's rays near this (see chunk)
MAX_BLOCK = 4096  # samples per block: a block's calls cost ~10 us, ~2 ns a sample at this size
LANE_BLOCK = MAX_BLOCK + MAX_BLOCK // 2  # the most a block holds once its bounds move to bands (wavefront._band_start)
MIN_BLOCK = 256
BLOCKS_PER_THREAD = 4  # smaller blocks for small batches, so that every thread has some


class Whitted:
    """Shades camera samples of one scene; build once, call trace_samples per frame (one call at a time:
    calls from several threads take turns). aside: on a first run, the kernel compiled by a second process while
    the caller compiles its own (hmdrt.trace.compile_aside); the first trace waits for it."""

    def __init__(self, scene: Scene, threads: int | None = None, aside: bool = False):
        self._aside = compile_aside.start() if aside else None  # first: it has the whole set-up to run alongside
        retain_freed_memory()
        self.packed = pack(scene)
        self.tracer = Tracer(self.packed.geometry, threads)
        self.plan = light_plan(self.packed.lights, scene)
        self.max_depth = scene.max_depth
        self.secondary = scene.has_secondary
        self.n_point = len(self.packed.lights.point_position)
        per_hit = 1 + self.n_point + self.plan.area_total + self.plan.ao_samples
        self.chunk = max(4096, RAYS_PER_CHUNK // per_hit)  # samples a band of a caller's own arrays should hold
        self._scene = SceneArgs(
            self.tracer.scene.handle,
            self.tracer.args,
            self.packed.geometry,
            self.packed.materials,
            self.packed.lights,
            self.plan,
            self.packed.has_textures,
            self.max_depth,
            self.secondary,
        )
        self._lock = threading.Lock()
        self._empty = False  # empty_scene(): trace_samples answers every sample with a miss, tracing nothing
        self._no_gbuffer, self._no_light = GBuffer.empty(0), LightBuffer.empty(0)
        # one lane of scratch per tracer thread, with room for a block and its children at first, each growing to the
        # largest level it met (meter.NEED)
        first = LANE_BLOCK * (2 if self.secondary and self.max_depth else 1)
        self._lanes = [self._lane(first) for _ in range(self.tracer.threads)]
        if self._aside is not None:  # the other part of the steps' kernels, then the second process compiles the tracer
            try:
                self.compile_part(1 - compile_aside.PART)
            finally:
                compile_aside.release(self._aside)

    @contextmanager
    def empty_scene(self) -> Iterator[None]:
        """Within it, trace_samples answers as if the scene were empty, without the tracer's kernel: every sample a
        miss (black, infinite depth, no light), its G-buffer and light buffer too. A start-up renders throwaway
        frames in it, so that a method's own kernels compile while the tracer's still compiles in a second process
        (hmdrt.trace.compile_aside), which a real trace waits for."""
        self._empty = True
        try:
            yield
        finally:
            self._empty = False

    def compile_part(self, part: int) -> None:
        """Part `part` of the kernels the tracer's steps call, compiled or loaded from the cache (compile_part)."""
        compile_part(self._scene, self._lanes[0], self._no_gbuffer, part)

    def _lane(self, capacity: int) -> Lane:
        return lane_empty(capacity, LANE_BLOCK, self.n_point, self.plan.area_total, self.plan.ao_samples)

    def _grow(self) -> None:
        """Give each lane that met a level larger than its scratch room for that level."""
        for t, lane in enumerate(self._lanes):
            need = int(lane.tally[meter.NEED])
            if need > len(lane.work.kr):
                self._lanes[t] = self._lane(need)

    def block(self, n: int) -> int:
        """Samples per block for a batch of n."""
        return min(MAX_BLOCK, max(MIN_BLOCK, -(-n // (self.tracer.threads * BLOCKS_PER_THREAD))))

    def close(self) -> None:
        if self._aside is not None:
            compile_aside.stop(self._aside)
            self._aside = None
        self.tracer.close()

    def __enter__(self) -> Whitted:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def trace_samples(
        self,
        camera: EyeCamera,
        xy: np.ndarray,
        keys: np.ndarray,
        stats: FrameStats,
        gbuffer: GBuffer | None = None,
        light: LightBuffer | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """Radiance (n, 3) float32 of the camera rays through pixel coordinates xy (n, 2), written into `out`
        (a C-contiguous (n, 3) float32 array) when given.

        keys (n,) int64 seed each sample's random decisions; gbuffer and light, if given, are filled for all n (a
        gbuffer in the attributes it keeps: GBuffer.empty).
        """
        xy = np.ascontiguousarray(xy, dtype=np.float32)
        keys = np.ascontiguousarray(keys, dtype=np.int64)
        n = len(xy)
        if xy.shape != (n, 2) or keys.shape != (n,):
            raise ValueError(f"xy must be (n, 2) and keys (n,), got {xy.shape} and {keys.shape}")
        if out is None:
            out = np.empty((n, 3), np.float32)
        elif out.shape != (n, 3) or out.dtype != np.float32 or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous ({n}, 3) float32 array, got {out.shape} {out.dtype}")
        for name, buffer in (("gbuffer", gbuffer and gbuffer.primary.depth), ("light", light and light.albedo)):
            if buffer is not None and len(buffer) < n:
                raise ValueError(f"{name} holds {len(buffer)} samples, fewer than the {n} traced")
        if gbuffer is not None and 0 < len(gbuffer.kept) < n:
            raise ValueError(f"gbuffer.kept holds {len(gbuffer.kept)} samples, fewer than the {n} traced")
        if n == 0:
            return out
        if self._empty:
            return _misses(out, gbuffer, light, n)
        frame = Frame(
            camera.rays(),
            xy,
            keys,
            out,
            self._no_gbuffer if gbuffer is None else gbuffer,
            self._no_light if light is None else light,
            gbuffer is not None,
            light is not None,
        )
        with self._lock:
            if self._aside is not None:  # the kernel in the cache before the first call, which then loads it
                compile_aside.finish(self._aside)
                self._aside = None
            for lane in self._lanes:
                lane.tally.fill(0)
            start = time.perf_counter_ns()
            trace(self._scene, frame, self._lanes, self.block(n), self.tracer.share)
            wall_ms = (time.perf_counter_ns() - start) / 1e6
            meter.credit(stats, wall_ms, [lane.tally for lane in self._lanes])
            self._grow()
        return out


def _misses(out: np.ndarray, gbuffer: GBuffer | None, light: LightBuffer | None, n: int) -> np.ndarray:
    """The first n samples' results as misses of an empty scene (Whitted.empty_scene): black, their G-buffer rows
    misses, no light."""
    out.fill(0.0)
    if gbuffer is not None:
        rows = gbuffer.rows(n)
        rows.primary.clear()
        rows.secondary.clear()
    if light is not None:
        light.irradiance[:n] = 0.0
        light.albedo[:n] = 0.0
    return out
