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
from hmdrt.scene.builtin import BUILTINS, KNOB_MINIMA, builtin_parameters, check_builtin_size
from hmdrt.scene.files import MESH_SUFFIXES, load_scene_file, mesh_scene
from hmdrt.scene.model import AreaLight, Mesh, Scene

COMMON_OPTIONS = {
    "max_depth": (int, 0, 16),
    "ao_samples": (int, 0, 1024),
    "ao_distance": (float, 1e-9, 1e9),
    "area_samples": (int, 1, 1024),
}

__all__ = ["BUILTINS", "Mesh", "Scene", "check_scene", "load_scene"]


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


def _apply_common(scene: Scene, common: dict[str, object]) -> Scene:
    for key, value in common.items():
        if key == "area_samples":
            scene.lights = [
                msgspec.structs.replace(l, samples=value) if isinstance(l, AreaLight) else l for l in scene.lights
            ]
        else:
            setattr(scene, key, value)
    return scene


def _builtin_knobs(name: str, options: dict[str, str]) -> dict[str, object]:
    """A built-in scene's knobs from its options, each parsed and in range, the scene within the size limit."""
    params = builtin_parameters(name)
    unknown = set(options) - set(params)
    if unknown:
        known = ", ".join([*params, *COMMON_OPTIONS])
        raise SceneError(f"scene {name!r} has no option {sorted(unknown)[0]!r}; options: {known}")
    minima = KNOB_MINIMA.get(name, {})
    knobs = {
        k: _parse_value(name, k, v, type(params[k]), minima.get(k), math.inf if k in minima else None)
        for k, v in options.items()
    }
    check_builtin_size(name, knobs)
    return knobs


def _checked(spec: str) -> tuple[str, dict[str, object] | None, dict[str, object]]:
    """A scene spec's name, its built-in knobs (None: a file) and its common options, each checked; nothing built."""
    name, _, query = spec.partition("?")
    try:
        options = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)))
    except ValueError:
        raise SceneError(f"scene options must look like ?key=value&key=value, got {query!r}") from None
    common = {
        k: _parse_value(name, k, options.pop(k), *COMMON_OPTIONS[k]) for k in list(options) if k in COMMON_OPTIONS
    }
    if name in BUILTINS:
        return name, _builtin_knobs(name, options), common
    suffix = Path(name).suffix.lower()
    if suffix == ".toml" or suffix in MESH_SUFFIXES:
        if options:
            raise SceneError(
                f"scene files take only {', '.join(COMMON_OPTIONS)} as options, not {sorted(options)[0]!r}"
            )
        return name, None, common
    raise SceneError(
        f"unknown scene {name!r}; built-in scenes: {', '.join(BUILTINS)}, "
        f"or a path to a .toml scene or a mesh file ({', '.join(MESH_SUFFIXES)})"
    )


def check_scene(spec: str) -> None:
    """A SceneError for a scene spec that load_scene would refuse by its name or options, or a built-in scene past
    the size limit, without building anything (a file's content is checked as it loads)."""
    _checked(spec)


def load_scene(spec: str) -> Scene:
    """A scene from a built-in name (with ?options), a .toml description or a mesh file."""
    name, knobs, common = _checked(spec)
    path = Path(name)
    if knobs is not None:
        try:
            scene = BUILTINS[name](**knobs)
        except (ValueError, MemoryError) as exc:
            raise SceneError(f"scene {name!r}: {exc}") from None
    else:
        scene = load_scene_file(path) if path.suffix.lower() == ".toml" else mesh_scene(path)
    return _apply_common(scene, common)
