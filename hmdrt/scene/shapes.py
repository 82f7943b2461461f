"""Procedural meshes for the built-in scenes: spheres, boxes, quads and parametric grids (tunnels).

trimesh is imported where a mesh is built, not with the module: it takes a second to import, which every
command line run (an error, --help) would otherwise pay before doing anything.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from hmdrt.scene.model import Mesh


def sphere(name: str, center, radius: float, material: str, subdivisions: int = 4) -> Mesh:
    """Icosphere with smooth normals and a spherical UV map; faces wound outward."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=subdivisions)
    unit = np.asarray(ico.vertices, dtype=np.float64)
    uv = np.stack([0.5 + np.arctan2(unit[:, 0], unit[:, 2]) / (2 * np.pi), 0.5 + np.arcsin(unit[:, 1]) / np.pi], axis=1)
    return Mesh(
        name, unit * radius + np.asarray(center, dtype=np.float64), np.asarray(ico.faces), material, unit.copy(), uv
    )


def box(name: str, lo, hi, material: str) -> Mesh:
    """Axis-aligned box from corner lo to corner hi, flat shaded, faces wound outward."""
    import trimesh

    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    b = trimesh.creation.box(bounds=np.stack([lo, hi]))
    return Mesh(name, np.asarray(b.vertices), np.asarray(b.faces), material)


def boxes(name: str, lo: np.ndarray, hi: np.ndarray, material: str) -> Mesh:
    """Many axis-aligned boxes (k, 3) corners as one flat-shaded mesh, built without a Python loop."""
    import trimesh

    unit = trimesh.creation.box(bounds=[[0, 0, 0], [1, 1, 1]])
    corners = np.asarray(unit.vertices)  # (8, 3) in {0, 1}
    verts = lo[:, None, :] + corners[None] * (hi - lo)[:, None, :]
    faces = np.asarray(unit.faces)[None] + 8 * np.arange(len(lo))[:, None, None]
    return Mesh(name, verts.reshape(-1, 3), faces.reshape(-1, 3), material)


def quad(name: str, corner, edge_u, edge_v, material: str, uv_scale=(1.0, 1.0)) -> Mesh:
    """Parallelogram corner + s*edge_u + t*edge_v; normal edge_u x edge_v; UV (s, t) * uv_scale."""
    c, u, v = (np.asarray(a, dtype=np.float64) for a in (corner, edge_u, edge_v))
    verts = np.stack([c, c + u, c + u + v, c + v])
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64) * np.asarray(uv_scale)
    return Mesh(name, verts, np.array([[0, 1, 2], [0, 2, 3]]), material, uv=uv)


def grid(
    name: str,
    nu: int,
    nv: int,
    surface: Callable[[np.ndarray, np.ndarray], np.ndarray],
    material: str,
    uv_scale=(1.0, 1.0),
    wrap_u: bool = False,
) -> Mesh:
    """Smooth mesh of a parametric surface sampled on an nu x nv grid over (u, v) in [0, 1]^2.

    surface maps (k,) u and (k,) v to (k, 3) points. wrap_u closes the surface in u (a tube);
    the seam keeps duplicate vertices so UVs stay continuous.
    """
    import trimesh

    u, v = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    pts = surface(u.ravel(), v.ravel())
    if wrap_u:
        pts.reshape(nu + 1, nv + 1, 3)[-1] = pts.reshape(nu + 1, nv + 1, 3)[0]
    idx = np.arange((nu + 1) * (nv + 1)).reshape(nu + 1, nv + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    normals = np.array(trimesh.Trimesh(pts, faces, process=False).vertex_normals)
    if wrap_u:  # both copies of a seam vertex take the normal of the closed surface
        seam = normals.reshape(nu + 1, nv + 1, 3)
        joined = seam[0] + seam[-1]
        seam[0] = seam[-1] = joined / np.maximum(np.linalg.norm(joined, axis=1, keepdims=True), 1e-300)
    uv = np.stack([u.ravel(), v.ravel()], axis=1) * np.asarray(uv_scale)
    return Mesh(name, pts, faces, material, normals, uv)


def tunnel(
    name: str,
    radius: float,
    length: float,
    material: str,
    segments: int = 96,
    rings: int = 120,
    radius_fn: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None,
    z0: float = 0.0,
    uv_scale=(1.0, 1.0),
) -> Mesh:
    """Circular tube along -Z from z0, axis at the origin in x/y; radius_fn(theta, z) displaces the wall."""

    def surface(u, v):
        theta = 2 * np.pi * u
        z = z0 - v * length
        r = radius if radius_fn is None else radius_fn(theta, z)
        return np.stack([r * np.cos(theta), r * np.sin(theta), z], axis=1)

    return grid(name, segments, rings, surface, material, uv_scale, wrap_u=True)
