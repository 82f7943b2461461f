"""Pack a Scene into flat arrays for Embree and the numba shading kernels (built once per scene).

All triangles go into one Embree geometry; a triangle's object id is the index of its mesh.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hmdrt.errors import SceneError
from hmdrt.scene.model import MAX_OCTAVES, AreaLight, Checker, Image, Noise, PointLight, Scene

TEX_NONE, TEX_CHECKER, TEX_NOISE, TEX_IMAGE = 0, 1, 2, 3


class Geometry(NamedTuple):
    vertices: np.ndarray  # (nv, 3) float32
    faces: np.ndarray  # (nt, 3) int32
    face_normals: np.ndarray  # (nt, 3) float32, unit; zero for degenerate triangles
    vertex_normals: np.ndarray  # (nv, 3) float32; used where the mesh is smooth
    uv: np.ndarray  # (nv, 2) float32; zero where the mesh has none
    extent: np.ndarray  # (nt,) float32, largest |coordinate| of the triangle (sets the ray offset)
    tri_object: np.ndarray  # (nt,) int32 mesh index
    object_material: np.ndarray  # (nm,) int32
    object_smooth: np.ndarray  # (nm,) bool
    object_has_uv: np.ndarray  # (nm,) bool


class Materials(NamedTuple):
    diffuse: np.ndarray  # (k, 3) float32
    specular: np.ndarray  # (k,)
    shininess: np.ndarray
    reflectance: np.ndarray
    transmittance: np.ndarray
    ior: np.ndarray
    emission: np.ndarray  # (k, 3)
    tex_kind: np.ndarray  # (k,) int32, TEX_*
    tex_world: np.ndarray  # (k,) bool: world-space rather than UV lookup
    tex_scale: np.ndarray
    tex_color0: np.ndarray  # (k, 3)
    tex_color1: np.ndarray
    tex_octaves: np.ndarray  # (k,) int32
    tex_seed: np.ndarray  # (k,) int32
    tex_offset: np.ndarray  # (k,) int64 into texels
    tex_height: np.ndarray  # (k,) int32
    tex_width: np.ndarray
    texels: np.ndarray  # (total, 3) float32, linear


class Lights(NamedTuple):
    point_position: np.ndarray  # (p, 3) float64
    point_intensity: np.ndarray  # (p, 3)
    area_corner: np.ndarray  # (a, 3)
    area_u: np.ndarray
    area_v: np.ndarray
    area_normal: np.ndarray  # unit, the emitting side
    area_size: np.ndarray  # (a,) m^2
    area_radiance: np.ndarray  # (a, 3)
    area_samples: np.ndarray  # (a,) int32


class PackedScene(NamedTuple):
    geometry: Geometry
    materials: Materials
    lights: Lights
    has_textures: np.ndarray  # (k,) bool, per material (the G-buffer's texture flag)


def _geometry(scene: Scene, material_index: dict[str, int]) -> Geometry:
    verts, faces, vnorm, uvs, tri_obj, obj_mat, smooth, has_uv = [], [], [], [], [], [], [], []
    base = 0
    for i, m in enumerate(scene.meshes):
        if m.material not in material_index:
            raise SceneError(
                f"mesh {m.name!r} uses unknown material {m.material!r}; materials: {', '.join(material_index)}"
            )
        v = np.asarray(m.vertices, dtype=np.float64)
        f = np.asarray(m.faces, dtype=np.int64)
        if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3:
            raise SceneError(f"mesh {m.name!r} must have (n, 3) vertices and (m, 3) faces")
        if not np.all(np.isfinite(v)):
            raise SceneError(f"mesh {m.name!r} has non-finite vertex coordinates")
        if len(f) and (f.min() < 0 or f.max() >= len(v)):
            raise SceneError(f"mesh {m.name!r} has face indices outside its {len(v)} vertices")
        verts.append(v)
        faces.append(f + base)
        vnorm.append(np.zeros_like(v) if m.normals is None else np.nan_to_num(m.normals))
        uvs.append(np.zeros((len(v), 2)) if m.uv is None else np.nan_to_num(m.uv))
        tri_obj.append(np.full(len(f), i, dtype=np.int32))
        obj_mat.append(material_index[m.material])
        smooth.append(m.normals is not None)
        has_uv.append(m.uv is not None)
        base += len(v)
    v = np.concatenate(verts) if verts else np.zeros((0, 3))
    f = np.concatenate(faces) if faces else np.zeros((0, 3), dtype=np.int64)
    if len(v) >= 2**31 or len(f) >= 2**31:
        raise SceneError("scene exceeds 2^31 vertices or triangles")
    tri = v[f]  # (nt, 3, 3) float64
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    return Geometry(
        v.astype(np.float32),
        f.astype(np.int32),
        n.astype(np.float32),
        (np.concatenate(vnorm) if vnorm else np.zeros((0, 3))).astype(np.float32),
        (np.concatenate(uvs) if uvs else np.zeros((0, 2))).astype(np.float32),
        np.abs(tri).max(axis=(1, 2)).astype(np.float32) if len(f) else np.zeros(0, np.float32),
        np.concatenate(tri_obj) if tri_obj else np.zeros(0, np.int32),
        np.array(obj_mat, dtype=np.int32),
        np.array(smooth, dtype=bool),
        np.array(has_uv, dtype=bool),
    )


def _column(items: list, get, dtype=np.float32, width: int | None = None) -> np.ndarray:
    """One field of every item as an array of shape (len(items),) or (len(items), width)."""
    shape = (len(items),) if width is None else (len(items), width)
    return np.array([get(x) for x in items], dtype=dtype).reshape(shape)


def _texture_field(material, attr: str, default):
    return getattr(material.texture, attr, default)


def _texture_images(scene: Scene, mats: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Image textures concatenated into one texel array, with each material's offset, height and width."""
    offsets, heights, widths, chunks, total = [], [], [], [], 0
    for m in mats:
        img = None
        if isinstance(m.texture, Image):
            if m.texture.image not in scene.images:
                raise SceneError(f"texture image {m.texture.image!r} is not loaded")
            img = np.asarray(scene.images[m.texture.image], dtype=np.float32)
            chunks.append(img.reshape(-1, 3))
        offsets.append(total)
        heights.append(0 if img is None else img.shape[0])
        widths.append(0 if img is None else img.shape[1])
        total += heights[-1] * widths[-1]
    texels = np.concatenate(chunks) if chunks else np.zeros((1, 3), dtype=np.float32)
    return np.array(offsets, np.int64), np.array(heights, np.int32), np.array(widths, np.int32), texels


def _octaves(material) -> int:
    """A noise texture's octave count, 1 .. MAX_OCTAVES (a Noise made in Python is not validated); 1 for others."""
    octaves = _texture_field(material, "octaves", 1)
    if not 1 <= octaves <= MAX_OCTAVES:
        raise SceneError(f"a noise texture has {octaves} octaves; 1 to {MAX_OCTAVES} are allowed")
    return octaves


def _materials(scene: Scene) -> Materials:
    mats = list(scene.materials.values())
    kinds = {type(None): TEX_NONE, Checker: TEX_CHECKER, Noise: TEX_NOISE, Image: TEX_IMAGE}
    no_colors = ((0.0, 0.0, 0.0), (0.0, 0.0, 0.0))
    return Materials(
        _column(mats, lambda m: m.diffuse, width=3),
        _column(mats, lambda m: m.specular),
        _column(mats, lambda m: m.shininess),
        _column(mats, lambda m: m.reflectance),
        _column(mats, lambda m: m.transmittance),
        _column(mats, lambda m: m.ior),
        _column(mats, lambda m: m.emission, width=3),
        _column(mats, lambda m: kinds[type(m.texture)], np.int32),
        _column(mats, lambda m: _texture_field(m, "mapping", "uv") == "world", bool),
        _column(mats, lambda m: _texture_field(m, "scale", 1.0)),
        _column(mats, lambda m: _texture_field(m, "colors", no_colors)[0], width=3),
        _column(mats, lambda m: _texture_field(m, "colors", no_colors)[1], width=3),
        _column(mats, _octaves, np.int32),
        _column(mats, lambda m: _texture_field(m, "seed", 0), np.int32),
        *_texture_images(scene, mats),
    )


def _lights(scene: Scene) -> Lights:
    points = [l for l in scene.lights if isinstance(l, PointLight)]
    areas = [l for l in scene.lights if isinstance(l, AreaLight)]
    edge_u = _column(areas, lambda a: a.edge_u, np.float64, 3)
    edge_v = _column(areas, lambda a: a.edge_v, np.float64, 3)
    cross = np.cross(edge_u, edge_v).reshape(len(areas), 3)
    size = np.linalg.norm(cross, axis=1)
    return Lights(
        _column(points, lambda p: p.position, np.float64, 3),
        _column(points, lambda p: p.intensity, np.float64, 3),
        _column(areas, lambda a: a.corner, np.float64, 3),
        edge_u,
        edge_v,
        cross / np.maximum(size, 1e-300)[:, None],
        size,
        _column(areas, lambda a: a.radiance, np.float64, 3),
        _column(areas, lambda a: a.samples, np.int32),
    )


def pack(scene: Scene) -> PackedScene:
    """Flat arrays of one scene; raises SceneError on references or data that cannot be traced."""
    index = {name: i for i, name in enumerate(scene.materials)}
    mats = _materials(scene)
    return PackedScene(_geometry(scene, index), mats, _lights(scene), mats.tex_kind != TEX_NONE)
