"""Direct lighting for Whitted shading: point lights with hard shadows, area lights with stratified
shadow samples, ambient occlusion with cosine-weighted samples, and Phong/Lambert local shading.

Ray generation and shading are separate passes around the occlusion queries. A ray that cannot
contribute (light behind the surface, no hit) gets tfar = -1, which Embree skips at almost no cost,
and it is not counted as traced.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.scene.model import Scene
from hmdrt.scene.pack import Lights
from hmdrt.trace.blocks import BLOCK
from hmdrt.trace.sampling import DIM_AO, DIM_AREA, cosine_hemisphere, grid_shape, stratified

AREA_SHORTEN = 1.0 - 1e-4  # stop area shadow rays just short of the emitter's own geometry


class RayBatch(NamedTuple):
    """Occlusion rays and, once traced, whether each found an occluder."""

    origins: np.ndarray  # (n, 3) float32
    directions: np.ndarray  # (n, 3) float32
    tfar: np.ndarray  # (n,) float32; -1 marks a ray that is not traced
    occluded: np.ndarray  # (n,) bool

    @classmethod
    def empty(cls, n: int) -> RayBatch:
        return cls(
            np.empty((n, 3), np.float32), np.empty((n, 3), np.float32), np.empty(n, np.float32), np.zeros(n, bool)
        )

    def active(self) -> int:
        return int(np.count_nonzero(self.tfar > 0))


class LightPlan(NamedTuple):
    """How a scene is lit: the per-hit shadow-ray layout (area light a owns columns
    area_base[a] .. area_base[a] + samples[a]), ambient occlusion, ambient and background."""

    area_base: np.ndarray  # (a,) int64
    area_nx: np.ndarray  # (a,) int64 strata per light
    area_ny: np.ndarray
    area_total: int
    ao_nx: int
    ao_ny: int
    ao_samples: int
    ao_distance: float
    ambient: np.ndarray  # (3,) float64
    background: np.ndarray  # (3,) float64


def light_plan(lights: Lights, scene: Scene) -> LightPlan:
    shapes = [grid_shape(int(s)) for s in lights.area_samples]
    ao = grid_shape(scene.ao_samples) if scene.ao_samples else (1, 1)
    return LightPlan(
        (np.cumsum(lights.area_samples) - lights.area_samples).astype(np.int64),
        np.array([s[0] for s in shapes], np.int64),
        np.array([s[1] for s in shapes], np.int64),
        int(lights.area_samples.sum()),
        ao[0],
        ao[1],
        scene.ao_samples,
        float(scene.ao_distance),
        np.asarray(scene.ambient, dtype=np.float64),
        np.asarray(scene.background, dtype=np.float64),
    )


@nb.njit(cache=True, nogil=True, inline="always")
def _spawn(origins, directions, far, j, position, ng, offset, i, tx, ty, tz, shorten):
    """Ray j from hit i towards (tx, ty, tz), starting on the side of the geometric normal."""
    off = offset[i]
    ox = position[i, 0] + ng[i, 0] * off
    oy = position[i, 1] + ng[i, 1] * off
    oz = position[i, 2] + ng[i, 2] * off
    dx, dy, dz = tx - ox, ty - oy, tz - oz
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    inv = 1.0 / dist if dist > 0.0 else 0.0
    origins[j, 0], origins[j, 1], origins[j, 2] = ox, oy, oz
    directions[j, 0], directions[j, 1], directions[j, 2] = dx * inv, dy * inv, dz * inv
    far[j] = dist * shorten if dist > 0.0 else -1.0


@nb.njit(cache=True, nogil=True, inline="always")
def _inactive(origins, directions, far, j):
    origins[j, 0] = origins[j, 1] = origins[j, 2] = 0.0
    directions[j, 0] = directions[j, 1] = 0.0
    directions[j, 2] = 1.0
    far[j] = -1.0


@nb.njit(cache=True, nogil=True)
def _light_rays_block(lights, plan, surf, keys, point, area, ao, start, stop):
    l_pos, a_corner, a_u, a_v, a_normal, a_samples = (
        lights.point_position,
        lights.area_corner,
        lights.area_u,
        lights.area_v,
        lights.area_normal,
        lights.area_samples,
    )
    a_base, a_nx, a_ny, a_total = plan.area_base, plan.area_nx, plan.area_ny, plan.area_total
    ao_n, ao_nx, ao_ny, ao_dist = plan.ao_samples, plan.ao_nx, plan.ao_ny, plan.ao_distance
    hits, position, ng, offset = surf.hit, surf.position, surf.normal_geometric, surf.offset
    p_org, p_dir, p_far = point.origins, point.directions, point.tfar
    a_org, a_dir, a_far = area.origins, area.directions, area.tfar
    o_org, o_dir, o_far = ao.origins, ao.directions, ao.tfar
    n_point = l_pos.shape[0]
    for i in range(start, stop):
        hit = hits[i]
        px, py, pz = position[i, 0], position[i, 1], position[i, 2]
        gx, gy, gz = ng[i, 0], ng[i, 1], ng[i, 2]
        for l in range(n_point):
            j = i * n_point + l
            lx, ly, lz = l_pos[l, 0], l_pos[l, 1], l_pos[l, 2]
            if hit and (lx - px) * gx + (ly - py) * gy + (lz - pz) * gz > 0.0:
                _spawn(p_org, p_dir, p_far, j, position, ng, offset, i, lx, ly, lz, 1.0)
            else:
                _inactive(p_org, p_dir, p_far, j)
        for a in range(a_base.shape[0]):
            for k in range(a_samples[a]):
                j = i * a_total + a_base[a] + k
                if not hit:
                    _inactive(a_org, a_dir, a_far, j)
                    continue
                s, t = stratified(keys[i], k, DIM_AREA + a, a_nx[a], a_ny[a])
                qx = a_corner[a, 0] + s * a_u[a, 0] + t * a_v[a, 0]
                qy = a_corner[a, 1] + s * a_u[a, 1] + t * a_v[a, 1]
                qz = a_corner[a, 2] + s * a_u[a, 2] + t * a_v[a, 2]
                lx, ly, lz = qx - px, qy - py, qz - pz
                facing_light = lx * gx + ly * gy + lz * gz > 0.0
                emits = lx * a_normal[a, 0] + ly * a_normal[a, 1] + lz * a_normal[a, 2] < 0.0
                if facing_light and emits:
                    _spawn(a_org, a_dir, a_far, j, position, ng, offset, i, qx, qy, qz, AREA_SHORTEN)
                else:
                    _inactive(a_org, a_dir, a_far, j)
        for k in range(ao_n):
            j = i * ao_n + k
            if not hit:
                _inactive(o_org, o_dir, o_far, j)
                continue
            s, t = stratified(keys[i], k, DIM_AO, ao_nx, ao_ny)
            dx, dy, dz = cosine_hemisphere(gx, gy, gz, s, t)
            _spawn(o_org, o_dir, o_far, j, position, ng, offset, i, px + dx, py + dy, pz + dz, 0.0)
            o_far[j] = ao_dist


@nb.njit(parallel=True, cache=True, nogil=True)
def light_rays_kernel(lights, plan, surf, keys, point, area, ao):
    """Fill the point-light, area-light and AO batches; hit i owns a fixed block of each."""
    n = surf.hit.shape[0]
    for b in nb.prange((n + BLOCK - 1) // BLOCK):
        _light_rays_block(lights, plan, surf, keys, point, area, ao, b * BLOCK, min(n, (b + 1) * BLOCK))


@nb.njit(cache=True, nogil=True, inline="always")
def _lit(ns, albedo, i, wlocal, ks, shininess, view, light, e):
    """Lambert + Phong (rgb) at hit i for a viewer along -view, light arriving from unit direction
    `light` with irradiance scale e (rgb, 1/r^2 included); vectors are 3-tuples."""
    nx, ny, nz = ns[i, 0], ns[i, 1], ns[i, 2]
    lx, ly, lz = light
    cos = nx * lx + ny * ly + nz * lz
    if cos <= 0.0:
        return 0.0, 0.0, 0.0
    spec = 0.0
    if ks > 0.0:
        # Phong: reflect the light direction about n and compare with the direction back to the viewer
        rv = -((2.0 * cos * nx - lx) * view[0] + (2.0 * cos * ny - ly) * view[1] + (2.0 * cos * nz - lz) * view[2])
        if rv > 0.0:
            spec = ks * rv**shininess
    w = wlocal * cos
    return e[0] * (w * albedo[i, 0] + spec), e[1] * (w * albedo[i, 1] + spec), e[2] * (w * albedo[i, 2] + spec)


@nb.njit(cache=True, nogil=True)
def _shade_block(lights, plan, mats, surf, dirs_in, point, area, ao, local, shadow_count, stochastic, start, stop):
    l_int, a_normal, a_size, a_rad, a_samples = (
        lights.point_intensity,
        lights.area_normal,
        lights.area_size,
        lights.area_radiance,
        lights.area_samples,
    )
    a_base, a_total, ao_n = plan.area_base, plan.area_total, plan.ao_samples
    refl, trans, spec_k, shin, emission = (
        mats.reflectance,
        mats.transmittance,
        mats.specular,
        mats.shininess,
        mats.emission,
    )
    hits, ns, albedo, material = surf.hit, surf.normal_shading, surf.albedo, surf.material
    p_dir, p_far, point_occ = point.directions, point.tfar, point.occluded
    a_dir, a_far, area_occ = area.directions, area.tfar, area.occluded
    ao_occ, ambient, background = ao.occluded, plan.ambient, plan.background
    n_point = l_int.shape[0]
    for i in range(start, stop):
        if not hits[i]:
            for c in range(3):
                local[i, c] = background[c]
                stochastic[i, c] = 0.0
            shadow_count[i] = 0
            continue
        k = material[i]
        wlocal = 1.0 - refl[k] - trans[k]
        ks, sh = spec_k[k], shin[k]
        view = (dirs_in[i, 0], dirs_in[i, 1], dirs_in[i, 2])
        ar = ag = ab = 0.0
        er = eg = eb = 0.0  # irradiance from the stochastic sources, for the light buffer
        shadowed = 0
        for l in range(n_point):
            j = i * n_point + l
            if p_far[j] <= 0.0:
                continue
            if point_occ[j]:
                shadowed += 1
                continue
            inv_r2 = 1.0 / (p_far[j] * p_far[j])
            e = (l_int[l, 0] * inv_r2, l_int[l, 1] * inv_r2, l_int[l, 2] * inv_r2)
            cr, cg, cb = _lit(ns, albedo, i, wlocal, ks, sh, view, (p_dir[j, 0], p_dir[j, 1], p_dir[j, 2]), e)
            ar, ag, ab = ar + cr, ag + cg, ab + cb
        for a in range(a_base.shape[0]):
            n_s = a_samples[a]
            for s in range(n_s):
                j = i * a_total + a_base[a] + s
                if a_far[j] <= 0.0:
                    continue
                if area_occ[j]:
                    shadowed += 1
                    continue
                lx, ly, lz = a_dir[j, 0], a_dir[j, 1], a_dir[j, 2]
                cos_l = -(lx * a_normal[a, 0] + ly * a_normal[a, 1] + lz * a_normal[a, 2])
                r = a_far[j] / AREA_SHORTEN
                scale = cos_l * a_size[a] / (r * r * n_s)
                e = (a_rad[a, 0] * scale, a_rad[a, 1] * scale, a_rad[a, 2] * scale)
                cr, cg, cb = _lit(ns, albedo, i, wlocal, ks, sh, view, (lx, ly, lz), e)
                ar, ag, ab = ar + cr, ag + cg, ab + cb
                cos_s = max(ns[i, 0] * lx + ns[i, 1] * ly + ns[i, 2] * lz, 0.0) * wlocal
                er, eg, eb = er + e[0] * cos_s, eg + e[1] * cos_s, eb + e[2] * cos_s
        open_sky = 1.0
        if ao_n > 0:
            blocked = 0
            for s in range(ao_n):
                if ao_occ[i * ao_n + s]:
                    blocked += 1
            open_sky = 1.0 - blocked / ao_n
        local[i, 0] = emission[k, 0] + ar + wlocal * ambient[0] * albedo[i, 0] * open_sky
        local[i, 1] = emission[k, 1] + ag + wlocal * ambient[1] * albedo[i, 1] * open_sky
        local[i, 2] = emission[k, 2] + ab + wlocal * ambient[2] * albedo[i, 2] * open_sky
        stochastic[i, 0] = er + wlocal * ambient[0] * open_sky
        stochastic[i, 1] = eg + wlocal * ambient[1] * open_sky
        stochastic[i, 2] = eb + wlocal * ambient[2] * open_sky
        shadow_count[i] = shadowed


@nb.njit(parallel=True, cache=True, nogil=True)
def shade_kernel(lights, plan, mats, surf, dirs_in, point, area, ao, local, shadow_count, stochastic):
    """Local radiance (n, 3) at each hit (background on misses), each hit's count of shadowed light
    samples, and the irradiance its area lights and ambient occlusion contribute (stochastic (n, 3)):
    the diffuse part of local from those sources is albedo x stochastic."""
    n = surf.hit.shape[0]
    for b in nb.prange((n + BLOCK - 1) // BLOCK):
        stop = min(n, (b + 1) * BLOCK)
        out = (local, shadow_count, stochastic)
        _shade_block(lights, plan, mats, surf, dirs_in, point, area, ao, *out, b * BLOCK, stop)
