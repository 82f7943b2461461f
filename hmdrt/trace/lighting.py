"""Direct lighting for Whitted shading: point lights with hard shadows, area lights with stratified
shadow samples, ambient occlusion with cosine-weighted samples, and Phong/Lambert local shading.

Ray generation and shading are separate steps around a block's occlusion queries. A ray that cannot
contribute (light behind the surface, no hit) gets tfar = -1: it is neither traced nor counted.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from hmdrt.kernels.jit import fused, inline, serial
from hmdrt.scene.model import Scene
from hmdrt.scene.pack import Lights
from hmdrt.trace.sampling import DIM_AO, DIM_AREA, cosine_hemisphere, grid_shape, stratified, tangent_frame

AREA_SHORTEN = 1.0 - 1e-4  # stop area shadow rays just short of the emitter's own geometry


class RayBatch(NamedTuple):
    """Occlusion rays and, once traced, whether each found an occluder."""

    origins: np.ndarray  # (n, 3) float32
    directions: np.ndarray  # (n, 3) float32
    tfar: np.ndarray  # (n,) float32; -1 marks a ray that is not traced
    occluded: np.ndarray  # (n,) bool


@serial
def batch_empty(n):
    return RayBatch(
        np.empty((n, 3), np.float32), np.empty((n, 3), np.float32), np.empty(n, np.float32), np.zeros(n, np.bool_)
    )


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


@inline
def _hit_frame(position, ng, offset, i):
    """Hit i's point and geometric normal, from flat (3 n,) views at unsigned indices, and where its light rays
    start: the point moved off the surface along the normal."""
    e = np.uint64(3) * np.uint64(i)
    px, py, pz = position[e], position[e + np.uint64(1)], position[e + np.uint64(2)]
    gx, gy, gz = ng[e], ng[e + np.uint64(1)], ng[e + np.uint64(2)]
    off = offset[i]
    return (px, py, pz), (gx, gy, gz), (px + gx * off, py + gy * off, pz + gz * off)


@inline
def _put_flat(origins, directions, j, ox, oy, oz, dx, dy, dz):
    """Ray j's origin and direction into flat (3 n,) views of the batch, at unsigned indices (no negative-index
    wraparound), which LLVM's vectoriser turns into interleaved stores."""
    e = np.uint64(3) * j
    origins[e], origins[e + np.uint64(1)], origins[e + np.uint64(2)] = ox, oy, oz
    directions[e], directions[e + np.uint64(1)], directions[e + np.uint64(2)] = dx, dy, dz


@inline
def _untraced(far, first, count):
    """Rays first .. first + count - 1, a miss's: marked by their tfar of -1 alone, as every ray that is not traced."""
    for j in range(first, first + count):
        far[j] = -1.0


@inline
def light_rays_block(lights, plan, surf, keys, point, area, ao, start, stop):
    """Fill the point-light, area-light and AO rays of hits [start, stop); hit i owns a fixed block of each.
    One pass per kind of source: a loop that holds all three runs twice as slow even where two are empty."""
    if lights.point_position.shape[0]:
        _point_rays(lights, surf, point, start, stop)
    if plan.area_total:
        _area_rays(lights, plan, surf, keys, area, start, stop)
    if plan.ao_samples:
        _ao_rays(plan, surf, keys, ao, start, stop)


@fused
def _point_rays(lights, surf, point, start, stop):
    """Each hit's ray to each point light, light by light in a loop over the hits that vectorises (flat views at
    unsigned indices); a ray that cannot reach its light (a miss, a light behind the surface) is marked by its tfar
    of -1 alone."""
    l_pos = lights.point_position
    hits, offset, p_far = surf.hit, surf.offset, point.tfar
    position, ng = surf.position.reshape(-1), surf.normal_geometric.reshape(-1)
    origins, directions = point.origins.reshape(-1), point.directions.reshape(-1)
    n_point = l_pos.shape[0]
    for l in range(n_point):
        lx, ly, lz = l_pos[l, 0], l_pos[l, 1], l_pos[l, 2]
        for i in range(start, stop):
            (px, py, pz), (gx, gy, gz), (ox, oy, oz) = _hit_frame(position, ng, offset, i)
            facing = (lx - px) * gx + (ly - py) * gy + (lz - pz) * gz > 0.0
            dx, dy, dz = lx - ox, ly - oy, lz - oz
            dist = math.sqrt(dx * dx + dy * dy + dz * dz)
            inv = np.divide(1.0, dist)
            j = np.uint64(i * n_point + l)
            _put_flat(origins, directions, j, ox, oy, oz, dx * inv, dy * inv, dz * inv)
            p_far[j] = dist if hits[i] & facing & (dist > 0.0) else -1.0


@fused
def _area_rays(lights, plan, surf, keys, area, start, stop):
    """Each hit's rays to its stratified points on each area light, in a loop over the samples that vectorises:
    flat stores at unsigned indices, and a ray the light cannot reach marked by tfar alone (its origin and
    direction are stored as they come)."""
    a_corner, a_u, a_v, a_normal, a_samples = (
        lights.area_corner,
        lights.area_u,
        lights.area_v,
        lights.area_normal,
        lights.area_samples,
    )
    a_base, a_nx, a_ny, a_total = plan.area_base, plan.area_nx, plan.area_ny, plan.area_total
    hits, offset, a_far = surf.hit, surf.offset, area.tfar
    position, ng = surf.position.reshape(-1), surf.normal_geometric.reshape(-1)
    origins, directions = area.origins.reshape(-1), area.directions.reshape(-1)
    for i in range(start, stop):
        if not hits[i]:
            _untraced(a_far, i * a_total, a_total)
            continue
        (px, py, pz), (gx, gy, gz), (ox, oy, oz) = _hit_frame(position, ng, offset, i)
        for a in range(a_base.shape[0]):
            cx, cy, cz = a_corner[a, 0], a_corner[a, 1], a_corner[a, 2]
            ux, uy, uz = a_u[a, 0], a_u[a, 1], a_u[a, 2]
            vx, vy, vz = a_v[a, 0], a_v[a, 1], a_v[a, 2]
            mx, my, mz = a_normal[a, 0], a_normal[a, 1], a_normal[a, 2]
            first = np.uint64(i * a_total + a_base[a])
            for k in range(np.int64(a_samples[a])):  # an int32 count would make k 32 bits wide: scatters
                s, t = stratified(keys[i], k, DIM_AREA + a, a_nx[a], a_ny[a])
                qx, qy, qz = cx + s * ux + t * vx, cy + s * uy + t * vy, cz + s * uz + t * vz
                lx, ly, lz = qx - px, qy - py, qz - pz
                facing_light = lx * gx + ly * gy + lz * gz > 0.0
                emits = lx * mx + ly * my + lz * mz < 0.0
                dx, dy, dz = qx - ox, qy - oy, qz - oz
                dist = math.sqrt(dx * dx + dy * dy + dz * dz)
                inv = np.divide(1.0, dist)
                j = first + np.uint64(k)
                _put_flat(origins, directions, j, ox, oy, oz, dx * inv, dy * inv, dz * inv)
                a_far[j] = dist * AREA_SHORTEN if facing_light & emits & (dist > 0.0) else -1.0


@fused
def _ao_rays(plan, surf, keys, ao, start, stop):
    """Each hit's cosine-weighted AO rays about its geometric normal, in a loop over the samples that vectorises
    (flat stores at unsigned indices)."""
    ao_n, ao_nx, ao_ny, ao_dist = plan.ao_samples, plan.ao_nx, plan.ao_ny, plan.ao_distance
    hits, offset, o_far = surf.hit, surf.offset, ao.tfar
    position, ng = surf.position.reshape(-1), surf.normal_geometric.reshape(-1)
    origins, directions = ao.origins.reshape(-1), ao.directions.reshape(-1)
    for i in range(start, stop):
        if not hits[i]:
            _untraced(o_far, i * ao_n, ao_n)
            continue
        _, (gx, gy, gz), (ox, oy, oz) = _hit_frame(position, ng, offset, i)
        normal = (np.float64(gx), np.float64(gy), np.float64(gz))
        tangent, bitangent = tangent_frame(normal[0], normal[1], normal[2])
        first = np.uint64(i * ao_n)
        for k in range(ao_n):
            s, t = stratified(keys[i], k, DIM_AO, ao_nx, ao_ny)
            dx, dy, dz = cosine_hemisphere(normal, tangent, bitangent, s, t)
            j = first + np.uint64(k)
            _put_flat(origins, directions, j, ox, oy, oz, dx, dy, dz)
            o_far[j] = ao_dist


@inline
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


@inline
def shade_block(lights, plan, mats, surf, dirs_in, point, area, ao, acc, local, shadow_count, stochastic, start, stop):
    """Local radiance (n, 3) at hits [start, stop) (background on misses), each hit's count of shadowed light
    samples, and the irradiance its area lights and ambient occlusion contribute (stochastic (n, 3)):
    the diffuse part of local from those sources is albedo x stochastic. acc (n, 6) float64: scratch for the
    sums that one pass per kind of source hands on (radiance rgb, stochastic irradiance rgb), added in the
    same order as one pass over all sources would; without area lights the point lights' pass finishes each hit
    itself, its sums never leaving the registers."""
    finish = plan.area_total == 0
    out = (acc, local, stochastic, shadow_count)
    _shade_points(lights, plan, mats, surf, dirs_in, point, ao, out, finish, start, stop)
    if not finish:
        _shade_areas(lights, plan, mats, surf, dirs_in, area, acc, shadow_count, start, stop)
        _shade_finish(plan, mats, surf, ao, acc, local, stochastic, start, stop)


@inline
def _material_terms(mats, surf, dirs_in, i):
    k = np.uint64(surf.material[i])
    wlocal = 1.0 - mats.reflectance[k] - mats.transmittance[k]
    return wlocal, mats.specular[k], mats.shininess[k], (dirs_in[i, 0], dirs_in[i, 1], dirs_in[i, 2])


@inline
def _open_sky(ao_occluded, ao_n, i):
    """The share of hit i's AO rays that found no occluder (1 without AO)."""
    if ao_n == 0:
        return 1.0
    blocked = 0
    for s in range(ao_n):
        blocked += 1 if ao_occluded[i * np.uint64(ao_n) + np.uint64(s)] else 0
    return 1.0 - blocked / ao_n


@inline
def _finished(emission, ambient, albedo, wlocal, open_sky, sums):
    """A hit's local radiance and stochastic irradiance (rgb each) from its light sums (radiance rgb, stochastic
    irradiance rgb), its emission, albedo and local weight (rgb tuples and a value) and the ambient light (rgb),
    which its AO rays dim by the sky they find (open_sky)."""
    ar, ag, ab, er, eg, eb = sums
    return (
        emission[0] + ar + wlocal * ambient[0] * albedo[0] * open_sky,
        emission[1] + ag + wlocal * ambient[1] * albedo[1] * open_sky,
        emission[2] + ab + wlocal * ambient[2] * albedo[2] * open_sky,
        er + wlocal * ambient[0] * open_sky,
        eg + wlocal * ambient[1] * open_sky,
        eb + wlocal * ambient[2] * open_sky,
    )


@serial
def _shade_points(lights, plan, mats, surf, dirs_in, point, ao, out, finish, start, stop):
    """The point lights' sums at hits [start, stop) into acc, or, with `finish`, each hit finished from them
    (_finished) where no other pass adds to them; out: (acc, local, stochastic, shadow_count)."""
    acc, local, stochastic, shadow_count = out
    emission, material, ambient, background = mats.emission, surf.material, plan.ambient, plan.background
    ao_occluded, ao_n = ao.occluded, plan.ao_samples
    l_int = lights.point_intensity
    hits, ns, albedo = surf.hit, surf.normal_shading, surf.albedo
    p_dir, p_far, point_occ = point.directions, point.tfar, point.occluded
    n_point = l_int.shape[0]
    for i in range(start, stop):
        i = np.uint64(i)  # unsigned indices: no negative-index wraparound on the loads
        ar = ag = ab = 0.0
        shadowed = 0
        wlocal = 0.0
        if hits[i]:
            wlocal, ks, sh, view = _material_terms(mats, surf, dirs_in, i)
            for l in range(n_point):
                j = i * np.uint64(n_point) + np.uint64(l)
                if p_far[j] <= 0.0:
                    continue
                if point_occ[j]:
                    shadowed += 1
                    continue
                inv_r2 = 1.0 / (p_far[j] * p_far[j])
                e = (l_int[l, 0] * inv_r2, l_int[l, 1] * inv_r2, l_int[l, 2] * inv_r2)
                cr, cg, cb = _lit(ns, albedo, i, wlocal, ks, sh, view, (p_dir[j, 0], p_dir[j, 1], p_dir[j, 2]), e)
                ar, ag, ab = ar + cr, ag + cg, ab + cb
        shadow_count[i] = shadowed
        if not finish:
            acc[i, 0], acc[i, 1], acc[i, 2] = ar, ag, ab
            acc[i, 3] = acc[i, 4] = acc[i, 5] = 0.0
        elif hits[i]:
            k = np.uint64(material[i])
            values = _finished(
                (emission[k, 0], emission[k, 1], emission[k, 2]), (ambient[0], ambient[1], ambient[2]),
                (albedo[i, 0], albedo[i, 1], albedo[i, 2]), wlocal, _open_sky(ao_occluded, ao_n, i),
                (ar, ag, ab, 0.0, 0.0, 0.0),
            )  # fmt: skip
            local[i, 0], local[i, 1], local[i, 2], stochastic[i, 0], stochastic[i, 1], stochastic[i, 2] = values
        else:
            for c in range(3):
                local[i, c], stochastic[i, c] = background[c], 0.0


@serial
def _shade_areas(lights, plan, mats, surf, dirs_in, area, acc, shadow_count, start, stop):
    a_normal, a_size, a_rad, a_samples = lights.area_normal, lights.area_size, lights.area_radiance, lights.area_samples
    a_base, a_total = plan.area_base, plan.area_total
    hits, ns, albedo = surf.hit, surf.normal_shading, surf.albedo
    a_dir, a_far, area_occ = area.directions, area.tfar, area.occluded
    for i in range(start, stop):
        if not hits[i]:
            continue
        wlocal, ks, sh, view = _material_terms(mats, surf, dirs_in, i)
        ar, ag, ab, er, eg, eb = acc[i, 0], acc[i, 1], acc[i, 2], acc[i, 3], acc[i, 4], acc[i, 5]
        shadowed = shadow_count[i]
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
        acc[i, 0], acc[i, 1], acc[i, 2], acc[i, 3], acc[i, 4], acc[i, 5] = ar, ag, ab, er, eg, eb
        shadow_count[i] = shadowed


@serial
def _shade_finish(plan, mats, surf, ao, acc, local, stochastic, start, stop):
    """Each hit in [start, stop) finished from the sums the passes before left in acc (_finished)."""
    hits, material, albedo, refl, trans = surf.hit, surf.material, surf.albedo, mats.reflectance, mats.transmittance
    emission, ambient, background = mats.emission, plan.ambient, plan.background
    ao_occluded, ao_n = ao.occluded, plan.ao_samples
    for i in range(start, stop):
        i = np.uint64(i)  # unsigned indices: no negative-index wraparound on the loads
        if not hits[i]:
            for c in range(3):
                local[i, c], stochastic[i, c] = background[c], 0.0
            continue
        k = np.uint64(material[i])
        values = _finished(
            (emission[k, 0], emission[k, 1], emission[k, 2]), (ambient[0], ambient[1], ambient[2]),
            (albedo[i, 0], albedo[i, 1], albedo[i, 2]), 1.0 - refl[k] - trans[k], _open_sky(ao_occluded, ao_n, i),
            (acc[i, 0], acc[i, 1], acc[i, 2], acc[i, 3], acc[i, 4], acc[i, 5]),
        )  # fmt: skip
        local[i, 0], local[i, 1], local[i, 2], stochastic[i, 0], stochastic[i, 1], stochastic[i, 2] = values
