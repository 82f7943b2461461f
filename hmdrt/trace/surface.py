"""From Embree hits to shading records: exact hit points, facing normals, albedo and the ray offset.

The hit point is rebuilt from the barycentrics in float64 (not o + t*d), so its error is bounded by
the triangle's own coordinates. New rays start OFFSET_REL x (largest |coordinate| of the triangle)
off the surface, a relative offset that holds at any scene scale (tested at 1e-4 m and 1e4 m).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from hmdrt.kernels.jit import serial
from hmdrt.trace.textures import texture_block

OFFSET_REL = 2.0**-16  # ~512 float32 ulps of the triangle's coordinates


class Surface(NamedTuple):
    """Shading records of n rays (valid where hit is True)."""

    hit: np.ndarray  # (n,) bool
    position: np.ndarray  # (n, 3) float64
    normal_geometric: np.ndarray  # (n, 3) float32, unit, facing the incoming ray
    normal_shading: np.ndarray  # (n, 3) float32, unit, same side as normal_geometric
    entering: np.ndarray  # (n,) bool: the ray arrived on the outward (front-face) side
    texcoord: np.ndarray  # (n, 3) float64: (u, v, 0), or the position for world-mapped textures
    albedo: np.ndarray  # (n, 3) float32 = diffuse x texture
    material: np.ndarray  # (n,) int32
    object_id: np.ndarray  # (n,) int32, -1 on a miss
    offset: np.ndarray  # (n,) float32, metres
    lookup: np.ndarray  # (4, n) float64: texture_block's scratch for noise lookups
    lookup_ids: np.ndarray  # (3, n) int64: and theirs


@serial
def surface_empty(n):
    return Surface(
        np.empty(n, np.bool_),
        np.empty((n, 3)),
        np.empty((n, 3), np.float32),
        np.empty((n, 3), np.float32),
        np.empty(n, np.bool_),
        np.empty((n, 3)),
        np.empty((n, 3), np.float32),
        np.empty(n, np.int32),
        np.empty(n, np.int32),
        np.empty(n, np.float32),
        np.empty((4, n)),
        np.empty((3, n), np.int64),
    )


@serial
def surface_block(geo, mats, directions, prim, bu, bv, out, start, stop):
    """Fill rows [start, stop) of `out` (a Surface) from the hits (prim, bu, bv) of rays with the given directions."""
    faces, verts, fnorm, vnorm, uvs = geo.faces, geo.vertices, geo.face_normals, geo.vertex_normals, geo.uv
    extent, tri_object, obj_mat, obj_smooth, obj_uv = (
        geo.extent,
        geo.tri_object,
        geo.object_material,
        geo.object_smooth,
        geo.object_has_uv,
    )
    tex_world = mats.tex_world
    hit, position, ng, ns, entering, texcoord, albedo, material, object_id, offset, lookup, lookup_ids = out
    for i in range(start, stop):
        i = np.uint64(i)  # unsigned indices: numba adds no negative-index wraparound to their loads
        p = prim[i]
        if p < 0:
            hit[i] = False
            object_id[i] = -1
            continue
        hit[i] = True
        p = np.uint64(p)
        i0, i1, i2 = np.uint64(faces[p, 0]), np.uint64(faces[p, 1]), np.uint64(faces[p, 2])
        u, v = float(bu[i]), float(bv[i])
        w = 1.0 - u - v
        for c in range(3):
            position[i, c] = w * verts[i0, c] + u * verts[i1, c] + v * verts[i2, c]
        dx, dy, dz = directions[i, 0], directions[i, 1], directions[i, 2]
        nx, ny, nz = fnorm[p, 0], fnorm[p, 1], fnorm[p, 2]
        if nx == 0.0 and ny == 0.0 and nz == 0.0:  # degenerate triangle: face the ray
            nx, ny, nz = -dx, -dy, -dz
        dn = dx * nx + dy * ny + dz * nz
        entering[i] = dn < 0.0
        flip = 1.0 if dn < 0.0 else -1.0
        nx, ny, nz = nx * flip, ny * flip, nz * flip
        ng[i, 0], ng[i, 1], ng[i, 2] = nx, ny, nz
        o = tri_object[p]
        obj = np.uint64(o)
        sx, sy, sz = nx, ny, nz
        if obj_smooth[obj]:
            ax = w * vnorm[i0, 0] + u * vnorm[i1, 0] + v * vnorm[i2, 0]
            ay = w * vnorm[i0, 1] + u * vnorm[i1, 1] + v * vnorm[i2, 1]
            az = w * vnorm[i0, 2] + u * vnorm[i1, 2] + v * vnorm[i2, 2]
            length = math.sqrt(ax * ax + ay * ay + az * az)
            if length > 0.0:
                s = 1.0 / length if ax * nx + ay * ny + az * nz >= 0.0 else -1.0 / length
                sx, sy, sz = ax * s, ay * s, az * s
        ns[i, 0], ns[i, 1], ns[i, 2] = sx, sy, sz
        k = obj_mat[obj]
        material[i], object_id[i] = k, o
        if tex_world[np.uint64(k)] or not obj_uv[obj]:
            for c in range(3):
                texcoord[i, c] = position[i, c]
        else:
            texcoord[i, 0] = w * uvs[i0, 0] + u * uvs[i1, 0] + v * uvs[i2, 0]
            texcoord[i, 1] = w * uvs[i0, 1] + u * uvs[i1, 1] + v * uvs[i2, 1]
            texcoord[i, 2] = 0.0
        offset[i] = max(extent[p], 1e-30) * OFFSET_REL
    texture_block(mats, material, texcoord, hit, albedo, lookup, lookup_ids, start, stop)
