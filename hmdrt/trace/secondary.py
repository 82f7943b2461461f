"""Secondary rays of Whitted ray tracing: mirror reflection and Fresnel-weighted refraction.

Children are written compactly (count, prefix sum, write) since only reflective or refractive hits
spawn them. A child carries throughput = parent throughput x its weight, and the weights of a hit's
children sum to at most 1 (trace.bsdf.split), so energy never rises through a bounce.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hmdrt.kernels.jit import inline, serial
from hmdrt.kernels.rng import hash32
from hmdrt.trace.bsdf import reflect, refract, split

MIN_THROUGHPUT = 1e-4  # children whose every channel would carry less than this are not traced


class Rays(NamedTuple):
    """A wavefront of rays and what they carry back to their pixel sample."""

    origins: np.ndarray  # (n, 3) float32
    directions: np.ndarray  # (n, 3) float32
    throughput: np.ndarray  # (n, 3) float32
    owner: np.ndarray  # (n,) int64 index of the sample the ray belongs to
    key: np.ndarray  # (n,) int64 random stream of the ray
    principal: np.ndarray  # (n,) bool: the heavier child of its parent (the "first secondary hit")
    through: np.ndarray  # (n,) bool: a refracted ray (it left through the surface), not a reflected one


@serial
def rays_empty(n):
    return Rays(
        np.empty((n, 3), np.float32),
        np.empty((n, 3), np.float32),
        np.empty((n, 3), np.float32),
        np.empty(n, np.int64),
        np.empty(n, np.int64),
        np.empty(n, np.bool_),
        np.empty(n, np.bool_),
    )


@serial
def interaction_block(mats, surf, rays, spawn, kr_out, kt_out, counts, spawners, start, stop):
    """Weights of the reflected and refracted rays at hits [start, stop), and how many children each spawns; the
    hits that spawn any, in order, into spawners, and how many there are (the spawn passes read those alone)."""
    refl, trans, ior = mats.reflectance, mats.transmittance, mats.ior
    hits, ns, entering, material = surf.hit, surf.normal_shading, surf.entering, surf.material
    dirs, thr = rays.directions, rays.throughput
    n = 0
    for i in range(start, stop):
        i = np.uint64(i)  # unsigned indices: no negative-index wraparound on the loads
        kr_out[i] = kt_out[i] = 0.0
        counts[i] = 0
        if not hits[i]:
            continue
        k = np.uint64(material[i])
        if refl[k] <= 0.0 and trans[k] <= 0.0:
            continue
        cos_i = -(dirs[i, 0] * ns[i, 0] + dirs[i, 1] * ns[i, 1] + dirs[i, 2] * ns[i, 2])
        kr, kt = split(refl[k], trans[k], cos_i, 1.0 / ior[k] if entering[i] else ior[k])
        kr_out[i], kt_out[i] = kr, kt
        if spawn:
            peak = max(thr[i, 0], thr[i, 1], thr[i, 2])
            counts[i] = int(kr * peak > MIN_THROUGHPUT) + int(kt * peak > MIN_THROUGHPUT)
            if counts[i]:
                spawners[n] = i
                n += 1
    return n


@inline
def _child(out, j, surf, parent, i, direction, side, weight, key, principal):
    """Child ray j of hit i: leaves from the `side` (+1 out, -1 through) of the surface along `direction`."""
    off = surf.offset[i] * side
    for c in range(3):
        out.origins[j, c] = surf.position[i, c] + surf.normal_geometric[i, c] * off
        out.throughput[j, c] = parent.throughput[i, c] * weight
        out.directions[j, c] = direction[c]
    out.owner[j] = parent.owner[i]
    out.key[j] = key
    out.principal[j] = principal
    out.through[j] = side < 0.0


@serial
def spawn_block(mats, surf, rays, kr_in, kt_in, first, depth, out, spawners, n):
    """Write the children of the hits spawners[:n] (interaction_block) at out[first[i]:] (reflection first, then
    refraction)."""
    ior, ng, ns, entering, material = mats.ior, surf.normal_geometric, surf.normal_shading, surf.entering, surf.material
    dirs, thr, keys = rays.directions, rays.throughput, rays.key
    for m in range(n):
        i = np.uint64(spawners[m])
        kr, kt = kr_in[i], kt_in[i]
        peak = max(thr[i, 0], thr[i, 1], thr[i, 2])
        want_r, want_t = kr * peak > MIN_THROUGHPUT, kt * peak > MIN_THROUGHPUT  # one at least: it spawns
        dx, dy, dz = dirs[i, 0], dirs[i, 1], dirs[i, 2]
        gx, gy, gz = ng[i, 0], ng[i, 1], ng[i, 2]
        nx, ny, nz = ns[i, 0], ns[i, 1], ns[i, 2]
        j = first[i]
        principal_is_reflection = kr >= kt
        if want_r:
            rx, ry, rz = reflect(dx, dy, dz, nx, ny, nz)
            if rx * gx + ry * gy + rz * gz <= 0.0:  # the shading normal sent it below the surface
                rx, ry, rz = reflect(dx, dy, dz, gx, gy, gz)
            _child(out, j, surf, rays, i, (rx, ry, rz), 1.0, kr, hash32(keys[i], depth, 1), principal_is_reflection)
            j += 1
        if want_t:
            k = np.uint64(material[i])
            eta = 1.0 / ior[k] if entering[i] else ior[k]
            ok, tx, ty, tz = refract(dx, dy, dz, nx, ny, nz, eta)
            if not ok or tx * gx + ty * gy + tz * gz >= 0.0:
                ok, tx, ty, tz = refract(dx, dy, dz, gx, gy, gz, eta)
            if not ok:  # the shading and geometric normals disagree on TIR: send the share straight on
                tx, ty, tz = dx, dy, dz
            key = hash32(keys[i], depth, 2)
            _child(out, j, surf, rays, i, (tx, ty, tz), -1.0, kt, key, not principal_is_reflection)
