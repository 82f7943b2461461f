"""Whitted ray tracing of arbitrary camera samples, as a wavefront over bounce depth.

Every foveation method hands this its sample positions; nothing else casts or shades rays. Per
depth: intersect, build shading records, trace the shadow / area / AO rays the scene needs, shade,
then spawn reflected and refracted rays (Whitted recursion, default depth 3). Stages a scene cannot
use are not run (no point lights -> no "shadow", no mirrors or glass -> no "secondary").
"""

from __future__ import annotations

import numpy as np

from hmdrt.memory import retain_freed_memory
from hmdrt.optics.camera import EyeCamera
from hmdrt.scene.model import Scene
from hmdrt.scene.pack import pack
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.gbuffer import GBuffer, LightBuffer, store_kernel
from hmdrt.trace.lighting import RayBatch, light_plan, light_rays_kernel, shade_kernel
from hmdrt.trace.secondary import Rays, accumulate_kernel, interaction_kernel, spawn_kernel
from hmdrt.trace.surface import Surface, surface_kernel
from hmdrt.trace.tracer import Tracer

RAYS_PER_CHUNK = 1 << 20  # bounds memory: samples per chunk x rays per sample stays near this


class Whitted:
    """Shades camera samples of one scene; build once, call trace_samples per frame."""

    def __init__(self, scene: Scene, threads: int | None = None):
        retain_freed_memory()
        self.packed = pack(scene)
        self.tracer = Tracer(self.packed.geometry, threads)
        self.plan = light_plan(self.packed.lights, scene)
        self.max_depth = scene.max_depth
        self.secondary = scene.has_secondary
        self.n_point = len(self.packed.lights.point_position)
        per_hit = 1 + self.n_point + self.plan.area_total + self.plan.ao_samples
        self.chunk = max(4096, RAYS_PER_CHUNK // per_hit)

    def close(self) -> None:
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
    ) -> np.ndarray:
        """Radiance (n, 3) float32 of the camera rays through pixel coordinates xy (n, 2).

        keys (n,) int64 seed each sample's random decisions; gbuffer and light, if given, are filled for all n.
        """
        out = np.empty((len(xy), 3), dtype=np.float32)
        for s in range(0, len(xy), self.chunk):
            e = min(s + self.chunk, len(xy))
            with stats.stage("raygen"):
                n = e - s
                rays = Rays(
                    np.empty((n, 3), np.float32),
                    camera.directions(xy[s:e]),
                    np.ones((n, 3), np.float32),
                    np.arange(n, dtype=np.int64),
                    np.ascontiguousarray(keys[s:e], dtype=np.int64),
                    np.ones(n, bool),
                )
                rays.origins[:] = camera.position
            radiance = np.zeros((n, 3), dtype=np.float64)
            self._trace_wavefront(rays, radiance, stats, gbuffer, light, s)
            out[s:e] = radiance
        return out

    def _trace_wavefront(
        self,
        rays: Rays,
        radiance: np.ndarray,
        stats: FrameStats,
        gbuffer: GBuffer | None,
        light: LightBuffer | None,
        row0: int,
    ) -> None:
        for depth in range(self.max_depth + 1):
            n = len(rays.owner)
            if n == 0:
                return
            kind = "primary" if depth == 0 else "secondary"
            with stats.stage(kind):
                hits = self.tracer.intersect(rays.origins, rays.directions)
            stats.count(kind, n)
            with stats.stage("surface"):
                surf = Surface.empty(n)
                surface_kernel(
                    self.packed.geometry, self.packed.materials, rays.directions, hits.prim, hits.u, hits.v, surf
                )
            local, shadow_count, stochastic = self._shade(surf, rays, stats)
            with stats.stage("shade"):
                if depth == 0:
                    radiance += local
                    if light is not None:
                        light.irradiance[row0 : row0 + n] = stochastic
                        light.albedo[row0 : row0 + n] = np.where(surf.hit[:, None], surf.albedo, 0.0)
                else:
                    accumulate_kernel(radiance, rays, local)
            spawn = depth < self.max_depth and self.secondary
            if spawn or gbuffer is not None and depth <= 1:
                with stats.stage("secondary" if spawn else "gbuffer"):
                    kr, kt, counts = np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.int64)
                    interaction_kernel(self.packed.materials, surf, rays, spawn, kr, kt, counts)
            if gbuffer is not None and depth <= 1:
                with stats.stage("gbuffer"):
                    attrs = gbuffer.primary if depth == 0 else gbuffer.secondary
                    rows = rays.owner + row0 if depth == 0 else np.where(rays.principal, rays.owner + row0, -1)
                    store_kernel(attrs, rows, hits.t, surf, self.packed.has_textures, shadow_count, kr, kt)
            if not spawn:
                return
            with stats.stage("secondary"):
                first = np.cumsum(counts) - counts
                children = Rays.empty(int(counts.sum()))
                spawn_kernel(self.packed.materials, surf, rays, kr, kt, first, depth + 1, children)
            rays = children

    def _shade(self, surf, rays: Rays, stats: FrameStats) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Local radiance of every hit (background on misses), its count of shadowed light samples, and
        the irradiance of its stochastic sources (area lights, ambient occlusion)."""
        n = len(surf.hit)
        per_hit = (self.n_point, self.plan.area_total, self.plan.ao_samples)
        point, area, ao = (RayBatch.empty(n * k) for k in per_hit)
        if sum(per_hit):
            with stats.stage("lightgen"):
                light_rays_kernel(self.packed.lights, self.plan, surf, rays.key, point, area, ao)
        for kind, batch in (("shadow", point), ("area", area), ("ao", ao)):
            if len(batch.tfar):
                with stats.stage(kind):
                    batch.occluded[:] = self.tracer.occluded(batch.origins, batch.directions, batch.tfar)
                stats.count(kind, batch.active())
        local = np.empty((n, 3), np.float64)
        shadow_count = np.empty(n, np.int16)
        stochastic = np.empty((n, 3), np.float32)
        with stats.stage("shade"):
            args = (self.packed.lights, self.plan, self.packed.materials, surf, rays.directions, point, area, ao)
            shade_kernel(*args, local, shadow_count, stochastic)
        return local, shadow_count, stochastic
