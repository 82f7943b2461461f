"""Scenes from files: a TOML scene description, and OBJ/PLY/GLB/glTF meshes loaded through trimesh
with their materials and textures (diffuse colour and map, OBJ Ks/Ns, glTF base colour and emission)."""

from __future__ import annotations

import functools
import io
import os
from pathlib import Path
from typing import Annotated

import msgspec
import numpy as np
from PIL import Image as PILImage
from PIL import UnidentifiedImageError

from hmdrt.errors import SceneError
from hmdrt.files.configfile import MAX_TOML_BYTES, parse_toml, read_limited
from hmdrt.ranges import MAX_SCENE_TRIANGLES, refuse_large
from hmdrt.scene import shapes
from hmdrt.scene.model import Checker, Colour, Finite, Image, Light, Material, Mesh, PointLight, Radiance, Scene, Vec3
from hmdrt.spatial import Pose

MESH_SUFFIXES = (".obj", ".ply", ".glb", ".gltf", ".stl", ".off")
MAX_FILE_BYTES = 512 * 1024 * 1024  # refuse to parse anything larger
MAX_TEXTURE_PIXELS = 8192 * 8192


class _Spec(msgspec.Struct, frozen=True, forbid_unknown_fields=True, tag_field="kind"):
    pass


class SphereSpec(_Spec, tag="sphere"):
    center: Vec3
    radius: Annotated[float, msgspec.Meta(gt=0, le=1e9)]
    material: str
    subdivisions: Annotated[int, msgspec.Meta(ge=0, le=7)] = 4


class BoxSpec(_Spec, tag="box"):
    lo: Vec3
    hi: Vec3
    material: str


class QuadSpec(_Spec, tag="quad"):
    corner: Vec3
    edge_u: Vec3
    edge_v: Vec3
    material: str
    uv_scale: tuple[Finite, Finite] = (1.0, 1.0)


class MeshSpec(_Spec, tag="mesh"):
    path: str
    material: str | None = None  # overrides the file's own materials
    translate: Vec3 = (0.0, 0.0, 0.0)
    rotate_deg: Vec3 = (0.0, 0.0, 0.0)  # intrinsic X, then Y, then Z
    scale: Annotated[float, msgspec.Meta(gt=0, le=1e9)] = 1.0


class CameraSpec(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    position: Vec3 = (0.0, 1.6, 0.0)
    yaw_deg: Annotated[float, msgspec.Meta(ge=-360, le=360)] = 0.0
    pitch_deg: Annotated[float, msgspec.Meta(ge=-90, le=90)] = 0.0
    look_at: Vec3 | None = None


class SceneFile(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """The TOML scene description (see configs/scenes/ for examples)."""

    name: str = ""
    background: Radiance = (0.0, 0.0, 0.0)
    ambient: Colour = (0.0, 0.0, 0.0)
    max_depth: Annotated[int, msgspec.Meta(ge=0, le=16)] = 3
    ao_samples: Annotated[int, msgspec.Meta(ge=0, le=1024)] = 0
    ao_distance: Annotated[float, msgspec.Meta(gt=0, le=1e9)] = 1.0
    camera: CameraSpec = CameraSpec()
    materials: dict[str, Material] = {}
    objects: list[SphereSpec | BoxSpec | QuadSpec | MeshSpec] = []
    lights: list[Light] = []


def _read_bytes(path: Path, what: str, limit: int = MAX_FILE_BYTES) -> bytes:
    return read_limited(path, what, limit, SceneError, regular_only=True)


@functools.cache
def _capped_resolver() -> type:
    """trimesh's resolver of the files a mesh file names (OBJ materials and textures, glTF buffers and
    images), reading each under the same size cap as the mesh file itself. Made at first use: trimesh takes a
    second to import (hmdrt.scene.shapes)."""
    import trimesh

    class CappedResolver(trimesh.resolvers.FilePathResolver):
        def get(self, name: str) -> bytes:
            for candidate in (name.strip(), name.strip().lstrip("/"), os.path.split(name)[-1]):
                try:
                    path = self.absolute(candidate)
                except ValueError:
                    continue  # outside the mesh file's folder
                if path.exists():
                    return _read_bytes(path, "file named by a mesh file")
            raise FileNotFoundError(name)

        def namespaced(self, namespace: str) -> CappedResolver:
            return CappedResolver(os.path.join(self.parent, namespace), allow_anywhere=self.allow_anywhere)

    return CappedResolver


def _image_to_linear(image, source: Path) -> np.ndarray:
    """A PIL image (of a file, or one a mesh file holds) as linear float32 (h, w, 3), decoding sRGB."""
    if image.width * image.height > MAX_TEXTURE_PIXELS:
        raise SceneError(
            f"texture image of {source}: {image.width}x{image.height} pixels exceeds the limit of {MAX_TEXTURE_PIXELS}"
        )
    try:
        rgb = image.convert("RGB")  # PIL decodes the pixels only now
    except (OSError, SyntaxError, ValueError) as exc:  # truncated or corrupt image data
        raise SceneError(f"cannot decode a texture image of {source}: {exc}") from None
    srgb = np.asarray(rgb, dtype=np.float32) / 255.0
    return np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4).astype(np.float32)


def load_image(path: Path) -> np.ndarray:
    """An image file as linear float32 (h, w, 3)."""
    data = _read_bytes(path, "texture image")
    try:
        with PILImage.open(io.BytesIO(data)) as img:
            return _image_to_linear(img, path)
    # ValueError: a bad header field (PNG's IHDR, PPM's numbers, TIFF's dimensions)
    except (UnidentifiedImageError, OSError, ValueError, PILImage.DecompressionBombError) as exc:
        raise SceneError(f"cannot decode texture image {path}: {exc}") from None


def _file_material(visual, key: Path, images: dict[str, np.ndarray], seen: dict[int, str]) -> Material:
    """Our material for a trimesh visual: diffuse colour and map, OBJ Ks/Ns, glTF emission."""
    import trimesh

    mat = getattr(visual, "material", None)
    if mat is None:  # ColorVisuals: one main colour, stored as sRGB bytes
        rgb = np.asarray(visual.main_color[:3], dtype=np.float64) / 255.0
        return Material(diffuse=tuple(rgb**2.2))
    texture, diffuse, specular, shininess, emission = None, (1.0, 1.0, 1.0), 0.0, 32.0, (0.0, 0.0, 0.0)
    if isinstance(mat, trimesh.visual.material.PBRMaterial):
        image = mat.baseColorTexture
        if mat.baseColorFactor is not None:
            diffuse = tuple(np.asarray(mat.baseColorFactor[:3], dtype=np.float64) / 255.0)
        if mat.emissiveFactor is not None:
            emission = tuple(float(e) for e in np.clip(mat.emissiveFactor, 0, None))
    else:
        image = getattr(mat, "image", None)
        diffuse = tuple(np.asarray(mat.diffuse[:3], dtype=np.float64) / 255.0)
        ns = float(getattr(mat, "glossiness", 0.0) or 0.0)
        if ns >= 1.0 and mat.specular is not None:
            specular, shininess = float(np.mean(mat.specular[:3]) / 255.0), min(ns, 1e4)
    if image is not None and getattr(visual, "uv", None) is not None:
        if id(image) not in seen:
            seen[id(image)] = f"{key}#{len(seen)}"
            images[seen[id(image)]] = _image_to_linear(image, key)
        texture = Image(image=seen[id(image)])
    return Material(diffuse=diffuse, specular=specular, shininess=shininess, emission=emission, texture=texture)


def load_mesh_file(
    path: Path, material: str | None = None
) -> tuple[list[Mesh], dict[str, Material], dict[str, np.ndarray]]:
    """Meshes, materials and linear texture images of a mesh file, with its node transforms applied."""
    import trimesh

    data = _read_bytes(path, "mesh file")
    try:
        loaded = trimesh.load(
            trimesh.util.wrap_as_stream(data),
            file_type=path.suffix[1:].lower(),
            force="scene",
            resolver=_capped_resolver()(path),
        )
    except Exception as exc:  # trimesh raises many types for malformed files
        raise SceneError(f"cannot load mesh file {path}: {exc}") from None
    meshes, materials, images, seen = [], {}, {}, {}
    try:  # trimesh computes normals, UVs and transforms lazily: a malformed file can fail here too
        for node in loaded.graph.nodes_geometry:
            transform, geom_name = loaded.graph[node]
            geom = loaded.geometry[geom_name]
            if not isinstance(geom, trimesh.Trimesh) or len(geom.faces) == 0:
                continue
            name = f"{path.name}/{node}"
            if material is None:
                materials[name] = _file_material(geom.visual, path, images, seen)
            uv = getattr(geom.visual, "uv", None)
            mesh = Mesh(
                name,
                np.asarray(geom.vertices, dtype=np.float64),
                np.asarray(geom.faces, dtype=np.int64),
                material or name,
                np.asarray(geom.vertex_normals, dtype=np.float64),
                None if uv is None or len(uv) != len(geom.vertices) else np.asarray(uv, dtype=np.float64),
            )
            meshes.append(_checked(mesh.transformed(np.asarray(transform, dtype=np.float64)), path))
    except SceneError:
        raise
    except Exception as exc:
        raise SceneError(f"cannot load mesh file {path}: {exc}") from None
    if not meshes:
        raise SceneError(f"mesh file {path} holds no triangles")
    _check_triangles(f"mesh file {path} has", meshes)
    return meshes, materials, images


def _check_triangles(what: str, meshes: list[Mesh], planned: int = 0) -> None:
    """Refuse meshes (and `planned` triangles still to build) past MAX_SCENE_TRIANGLES before they are packed."""
    triangles = planned + sum(len(m.faces) for m in meshes)
    refuse_large(what, triangles, MAX_SCENE_TRIANGLES, "triangles", SceneError)


def _planned_triangles(spec: SphereSpec | BoxSpec | QuadSpec | MeshSpec) -> int:
    """The triangles a sphere, box or quad of a scene file makes; a mesh file's count once it is loaded."""
    if isinstance(spec, SphereSpec):
        return 20 * 4**spec.subdivisions  # an icosahedron, each face split in four per subdivision
    return {BoxSpec: 12, QuadSpec: 2}.get(type(spec), 0)


def _checked(mesh: Mesh, path: Path) -> Mesh:
    """The mesh, if its arrays have the shapes the tracer needs, finite values and faces that index vertices."""
    v, f, n, uv = mesh.vertices, mesh.faces, mesh.normals, mesh.uv
    if v.ndim != 2 or v.shape[1] != 3 or f.ndim != 2 or f.shape[1] != 3 or (n is not None and n.shape != v.shape):
        raise SceneError(f"mesh file {path}: {mesh.name} is not a triangle mesh")
    if f.min() < 0 or f.max() >= len(v):
        raise SceneError(f"mesh file {path}: {mesh.name} has faces that index no vertex")
    if not all(np.isfinite(a).all() for a in (v, n, uv) if a is not None):
        raise SceneError(f"mesh file {path}: {mesh.name} has non-finite vertices, normals or UVs")
    return mesh


def _object_meshes(spec, base: Path, scene: Scene) -> list[Mesh]:
    import trimesh

    if isinstance(spec, SphereSpec):
        return [shapes.sphere("sphere", spec.center, spec.radius, spec.material, spec.subdivisions)]
    if isinstance(spec, BoxSpec):
        if not np.all(np.asarray(spec.hi) > np.asarray(spec.lo)):
            raise SceneError("box needs hi > lo in every axis")
        return [shapes.box("box", spec.lo, spec.hi, spec.material)]
    if isinstance(spec, QuadSpec):
        return [shapes.quad("quad", spec.corner, spec.edge_u, spec.edge_v, spec.material, spec.uv_scale)]
    meshes, materials, images = load_mesh_file(base / spec.path, spec.material)
    scene.materials.update(materials)
    scene.images.update(images)
    rot = trimesh.transformations.euler_matrix(*np.radians(spec.rotate_deg), axes="rxyz")
    matrix = trimesh.transformations.translation_matrix(spec.translate) @ rot @ np.diag([spec.scale] * 3 + [1.0])
    return [m.transformed(matrix) for m in meshes]


def load_scene_file(path: Path) -> Scene:
    """Build a Scene from a TOML scene description; paths inside it are relative to the file."""
    try:
        spec = msgspec.convert(parse_toml(_read_bytes(path, "scene file", MAX_TOML_BYTES)), SceneFile)
    except msgspec.ValidationError as exc:
        raise SceneError(f"scene file {path}: {exc}") from None
    except ValueError as exc:  # not UTF-8, not TOML, or nested too deeply
        raise SceneError(f"scene file {path} is not valid TOML: {exc}") from None
    cam = spec.camera
    start = (
        Pose.look_at(cam.position, cam.look_at)
        if cam.look_at
        else Pose.looking(cam.position, cam.yaw_deg, cam.pitch_deg)
    )
    scene = Scene(
        spec.name or path.stem,
        [],
        dict(spec.materials),
        list(spec.lights),
        spec.background,
        spec.ambient,
        spec.ao_samples,
        spec.ao_distance,
        spec.max_depth,
        start,
    )
    for name, mat in spec.materials.items():
        if isinstance(mat.texture, Image):
            image = load_image(path.parent / mat.texture.image)  # first: SceneError for a path resolve() refuses
            key = str((path.parent / mat.texture.image).resolve())
            scene.images[key] = image
            scene.materials[name] = msgspec.structs.replace(
                mat, texture=msgspec.structs.replace(mat.texture, image=key)
            )
    planned = sum(_planned_triangles(obj) for obj in spec.objects)
    what = f"scene file {path} with {len(spec.objects)} objects makes"
    _check_triangles(what, [], planned)
    for i, obj in enumerate(spec.objects):
        planned -= _planned_triangles(obj)
        try:
            scene.meshes.extend(_object_meshes(obj, path.parent, scene))
        except SceneError as exc:
            raise SceneError(f"scene file {path}: objects[{i}]: {exc}") from None
        if isinstance(obj, MeshSpec):  # its triangles are known now
            _check_triangles(what, scene.meshes, planned)
    return scene


def mesh_scene(path: Path) -> Scene:
    """A studio scene around one mesh file: the model on a checker floor, framed by the camera, one light."""
    meshes, materials, images = load_mesh_file(path)
    lo = np.min([m.vertices.min(axis=0) for m in meshes], axis=0)
    hi = np.max([m.vertices.max(axis=0) for m in meshes], axis=0)
    centre, radius = (lo + hi) / 2, max(float(np.linalg.norm(hi - lo)) / 2, 1e-6)
    drop = np.eye(4)
    drop[:3, 3] = [-centre[0], -lo[1], -centre[2]]
    meshes = [m.transformed(drop) for m in meshes]
    materials["floor"] = Material(
        diffuse=(1, 1, 1), texture=Checker(colors=((0.3, 0.3, 0.3), (0.6, 0.6, 0.6)), scale=4 / radius)
    )
    meshes.append(
        shapes.quad(
            "floor",
            (-10 * radius, 0, 10 * radius),
            (20 * radius, 0, 0),
            (0, 0, -20 * radius),
            "floor",
            uv_scale=(20 * radius, 20 * radius),
        )
    )
    target = np.array([0.0, (hi[1] - lo[1]) / 2, 0.0])
    eye = target + np.array([0.0, 0.5 * radius, 2.0 * radius])
    light = PointLight(position=tuple(eye + [radius, 3 * radius, 0.5 * radius]), intensity=(12.0 * radius**2,) * 3)
    return Scene(
        path.stem,
        meshes,
        materials,
        [light],
        background=(0.35, 0.55, 0.85),
        ambient=(0.12, 0.12, 0.12),
        start=Pose.look_at(eye, target),
        images=images,
    )
