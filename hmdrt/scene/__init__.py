"""Scenes: built-in procedural scenes, TOML scene descriptions and mesh files.

load_scene("whitted"), load_scene("voxel_city?size=50&max_depth=2"), load_scene("room.toml"),
load_scene("model.glb"). Options after "?" are the built-in scene's knobs plus, for any scene,
max_depth, ao_samples, ao_distance and area_samples.
"""

from __future__ import annotations

import math
from pathlib import Path
from urllib.parse import parse_qsl

import msgspec

from hmdrt.errors import SceneError
from hmdrt.scene.builtin import BUILTINS, builtin_parameters
from hmdrt.scene.files import MESH_SUFFIXES, load_scene_file, mesh_scene
from hmdrt.scene.model import AreaLight, Mesh, Scene

COMMON_OPTIONS = {
    "max_depth": (int, 0, 16),
    "ao_samples": (int, 0, 1024),
    "ao_distance": (float, 1e-9, 1e9),
    "area_samples": (int, 1, 1024),
}

__all__ = ["BUILTINS", "Mesh", "Scene", "load_scene"]


def _parse_value(scene: str, key: str, text: str, kind: type, lo: float | None = None, hi: float | None = None):
    try:
        value = kind(text)
    except ValueError:
        raise SceneError(f"scene {scene!r}: option {key}={text!r} is not a valid {kind.__name__}") from None
    if isinstance(value, float) and not math.isfinite(value):
        raise SceneError(f"scene {scene!r}: option {key} must be finite")
    if lo is not None and not (lo <= value <= hi):
        raise SceneError(f"scene {scene!r}: option {key}={value} is outside [{lo}, {hi}]")
    return value


def _apply_common(scene: Scene, name: str, options: dict[str, str]) -> Scene:
    for key, text in options.items():
        kind, lo, hi = COMMON_OPTIONS[key]
        value = _parse_value(name, key, text, kind, lo, hi)
        if key == "area_samples":
            scene.lights = [
                msgspec.structs.replace(l, samples=value) if isinstance(l, AreaLight) else l for l in scene.lights
            ]
        else:
            setattr(scene, key, value)
    return scene


def load_scene(spec: str) -> Scene:
    """A scene from a built-in name (with ?options), a .toml description or a mesh file."""
    name, _, query = spec.partition("?")
    try:
        options = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)))
    except ValueError:
        raise SceneError(f"scene options must look like ?key=value&key=value, got {query!r}") from None
    common = {k: options.pop(k) for k in list(options) if k in COMMON_OPTIONS}
    path = Path(name)
    if name in BUILTINS:
        params = builtin_parameters(name)
        unknown = set(options) - set(params)
        if unknown:
            known = ", ".join([*params, *COMMON_OPTIONS])
            raise SceneError(f"scene {name!r} has no option {sorted(unknown)[0]!r}; options: {known}")
        kwargs = {k: _parse_value(name, k, v, type(params[k])) for k, v in options.items()}
        try:
            scene = BUILTINS[name](**kwargs)
        except (ValueError, MemoryError) as exc:
            raise SceneError(f"scene {name!r}: {exc}") from None
    elif path.suffix.lower() == ".toml" or path.suffix.lower() in MESH_SUFFIXES:
        if options:
            raise SceneError(
                f"scene files take only {', '.join(COMMON_OPTIONS)} as options, not {sorted(options)[0]!r}"
            )
        scene = load_scene_file(path) if path.suffix.lower() == ".toml" else mesh_scene(path)
    else:
        raise SceneError(
            f"unknown scene {name!r}; built-in scenes: {', '.join(BUILTINS)}, "
            f"or a path to a .toml scene or a mesh file ({', '.join(MESH_SUFFIXES)})"
        )
    return _apply_common(scene, name, common)
