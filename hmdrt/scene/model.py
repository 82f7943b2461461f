"""Scene model: materials, textures, lights, triangle meshes and the scene that holds them.

Materials, textures and lights are msgspec Structs so that a TOML scene description is validated
against the same definitions the built-in scenes use. Albedo = diffuse x texture. A material's
local (diffuse) weight is 1 - reflectance - transmittance, so no bounce can add energy.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

import msgspec
import numpy as np

from hmdrt.ranges import Finite, Fraction
from hmdrt.spatial import Pose

NonNegative = Annotated[float, msgspec.Meta(ge=0.0, le=1e12)]
Colour = tuple[Fraction, Fraction, Fraction]
Radiance = tuple[NonNegative, NonNegative, NonNegative]
Vec3 = tuple[Finite, Finite, Finite]
Mapping = Literal["uv", "world"]


MAX_OCTAVES = 12  # a noise texture's octaves at most: the texture kernels hold a table for each count


class _Struct(msgspec.Struct, frozen=True, forbid_unknown_fields=True, tag_field="kind"):
    pass


class Checker(_Struct, tag="checker"):
    """Two-colour checkerboard with `scale` cells per texture unit."""

    colors: tuple[Colour, Colour] = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    scale: Annotated[float, msgspec.Meta(gt=0, le=1e6)] = 1.0
    mapping: Mapping = "uv"


class Noise(_Struct, tag="noise"):
    """Fractal gradient noise blending two colours; `scale` is the base frequency per texture unit."""

    colors: tuple[Colour, Colour] = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))
    scale: Annotated[float, msgspec.Meta(gt=0, le=1e6)] = 1.0
    octaves: Annotated[int, msgspec.Meta(ge=1, le=MAX_OCTAVES)] = 4
    seed: Annotated[int, msgspec.Meta(ge=0, lt=2**31)] = 0
    mapping: Mapping = "uv"


class Image(_Struct, tag="image"):
    """An image looked up by UV with bilinear filtering and wrap-around; `image` keys Scene.images."""

    image: str
    scale: Annotated[float, msgspec.Meta(gt=0, le=1e6)] = 1.0
    mapping: Literal["uv"] = "uv"


Texture = Checker | Noise | Image


class Material(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Phong/Lambert surface with optional mirror reflection and Fresnel dielectric transmission."""

    diffuse: Colour = (0.8, 0.8, 0.8)
    specular: Fraction = 0.0
    shininess: Annotated[float, msgspec.Meta(ge=1.0, le=1e4)] = 32.0
    reflectance: Fraction = 0.0
    transmittance: Fraction = 0.0
    ior: Annotated[float, msgspec.Meta(ge=1.0, le=4.0)] = 1.5
    emission: Radiance = (0.0, 0.0, 0.0)
    texture: Texture | None = None

    def __post_init__(self) -> None:
        if self.reflectance + self.transmittance > 1.0:
            raise ValueError("reflectance + transmittance must not exceed 1")


class PointLight(_Struct, tag="point"):
    """Point light of radiant intensity `intensity` (falls off with the squared distance); hard shadows."""

    position: Vec3
    intensity: Radiance


class AreaLight(_Struct, tag="area"):
    """Parallelogram emitter corner + s*edge_u + t*edge_v, one-sided along edge_u x edge_v.

    Sampled with `samples` stratified shadow rays per shading point.
    """

    corner: Vec3
    edge_u: Vec3
    edge_v: Vec3
    radiance: Radiance
    samples: Annotated[int, msgspec.Meta(ge=1, le=1024)] = 8

    def __post_init__(self) -> None:
        if np.linalg.norm(np.cross(self.edge_u, self.edge_v)) == 0.0:
            raise ValueError("area light edges must span a parallelogram of non-zero area")


Light = PointLight | AreaLight


@dataclass
class Mesh:
    """A triangle mesh with one material. normals=None means flat shading with face normals."""

    name: str
    vertices: np.ndarray  # (n, 3) float64
    faces: np.ndarray  # (m, 3) int64
    material: str
    normals: np.ndarray | None = None  # (n, 3) unit vertex normals for smooth shading
    uv: np.ndarray | None = None  # (n, 2)

    def transformed(self, matrix: np.ndarray) -> Mesh:
        """This mesh under a 4x4 affine transform (normals by the inverse transpose)."""
        v = self.vertices @ matrix[:3, :3].T + matrix[:3, 3]
        n = None
        if self.normals is not None:
            n = self.normals @ np.linalg.inv(matrix[:3, :3])
            n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        return Mesh(self.name, v, self.faces, self.material, n, self.uv)


@dataclass
class Scene:
    """Everything the tracer needs; built once, then packed into flat arrays (scene.pack)."""

    name: str
    meshes: list[Mesh]
    materials: dict[str, Material]
    lights: list[Light] = field(default_factory=list)
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ambient: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ao_samples: int = 0
    ao_distance: float = 1.0
    max_depth: int = 3
    start: Pose = field(default_factory=Pose)
    images: dict[str, np.ndarray] = field(default_factory=dict)  # linear float32 (h, w, 3)

    @property
    def triangle_count(self) -> int:
        return sum(len(m.faces) for m in self.meshes)

    @property
    def has_secondary(self) -> bool:
        """Whether any material spawns reflection or refraction rays (and depth allows them)."""
        used = {m.material for m in self.meshes}
        return self.max_depth > 0 and any(
            self.materials[k].reflectance > 0 or self.materials[k].transmittance > 0 for k in used
        )
