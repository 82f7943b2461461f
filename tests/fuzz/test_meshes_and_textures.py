"""Fuzzing bytes and text from outside, meshes and textures (hmdrt.scene.files):
bad input never gets in, never crashes."""

from __future__ import annotations

import io
import json
import struct
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
import trimesh
from hypothesis import strategies as st
from PIL import Image as PILImage

from hmdrt.errors import ConfigError, SceneError
from hmdrt.replay import load_trace
from hmdrt.scene.files import MAX_FILE_BYTES as MAX_MESH_BYTES
from hmdrt.scene.files import MESH_SUFFIXES, load_image, load_mesh_file, load_scene_file
from tests.fuzz.common import (
    MESHES,
    error_names_file,
    fuzz,
    mutations,
    scratch,
)

pytestmark = [  # corrupt input makes PIL and trimesh warn about what they skip; expected here
    pytest.mark.filterwarnings("ignore::UserWarning:PIL"),
    pytest.mark.filterwarnings("ignore::RuntimeWarning:trimesh"),
]


def mesh_seeds() -> dict[str, bytes]:
    """A small textured-less box in every mesh format trimesh writes."""
    box = trimesh.creation.box()
    return {
        suffix: trimesh.exchange.export.export_mesh(box, None, suffix[1:])
        for suffix in MESH_SUFFIXES
        if suffix != ".gltf"
    }


MESH_SEEDS = {k: v.encode() if isinstance(v, str) else v for k, v in mesh_seeds().items()}


def mesh_outcome(path: Path) -> None:
    """load_mesh_file gives meshes with finite vertices, in-range faces and finite normals, or SceneError."""
    try:
        meshes, _, images = load_mesh_file(path)
    except SceneError as exc:
        error_names_file(exc, path)
        return
    for mesh in meshes:
        assert np.isfinite(mesh.vertices).all()
        assert mesh.faces.size and mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
        assert mesh.normals is None or np.isfinite(mesh.normals).all()
    for image in images.values():
        assert image.ndim == 3 and image.shape[2] == 3 and np.isfinite(image).all()


@fuzz(60, suffix=st.sampled_from(MESH_SUFFIXES), data=st.binary(max_size=300))
def test_mesh_file_of_any_bytes_is_meshes_or_scene_error(suffix, data):
    """Arbitrary bytes under every mesh suffix load as well-formed meshes or raise SceneError naming the file."""
    mesh_outcome(scratch("fuzz" + suffix, data))


@fuzz(100, case=st.sampled_from(sorted(MESH_SEEDS)).flatmap(lambda s: st.tuples(st.just(s), mutations(MESH_SEEDS[s]))))
def test_corrupted_mesh_files_are_meshes_or_scene_error(case):
    """A box in OBJ, PLY, STL, OFF and GLB, truncated or overwritten anywhere (counts, headers, indices), loads
    as well-formed meshes or raises SceneError."""
    suffix, data = case
    mesh_outcome(scratch("mutant" + suffix, data))


def png(width: int, height: int, idat: bytes = b"") -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def image_seeds() -> list[bytes]:
    """A 4 x 4 image in the formats PIL writes without extra libraries."""
    pixels = PILImage.fromarray((np.arange(48).reshape(4, 4, 3) * 5).astype(np.uint8))
    seeds = []
    for fmt in ("PNG", "JPEG", "GIF", "BMP", "TIFF", "PPM", "TGA"):
        out = io.BytesIO()
        pixels.save(out, fmt)
        seeds.append(out.getvalue())
    return seeds


@fuzz(80, data=st.one_of(st.binary(max_size=200), st.sampled_from(image_seeds()).flatmap(mutations)))
def test_texture_image_of_any_bytes_is_an_image_or_scene_error(data):
    """Arbitrary bytes, and PNG, JPEG, GIF, BMP, TIFF, PPM and TGA images corrupted anywhere, load as a finite
    linear RGB image or raise SceneError."""
    path = scratch("texture.png", data)
    try:
        image = load_image(path)
    except SceneError as exc:
        error_names_file(exc, path)
        return
    assert image.ndim == 3 and np.isfinite(image).all()


@pytest.mark.parametrize(
    "data",
    [
        b"\x89PNG\r\n\x1a\n\x00\x00\x00\x00IHDR",  # found by the extended run
        b"P6\n4 x\n255\n",
        b"P6\n4 4\n0\n",
    ],
)
def test_image_headers_pil_refuses_with_value_error_are_scene_errors(data):
    """Regression: PIL refuses some headers (a truncated PNG IHDR, PPM numbers that are not numbers, a PPM maxval
    of 0) with ValueError, which escaped load_image; now SceneError naming the file."""
    path = scratch("header.img", data)
    with pytest.raises(SceneError, match="header.img"):
        load_image(path)


def test_a_texture_over_the_pixel_limit_is_a_scene_error_naming_the_file():
    """Regression (found by a clean clone's run of the fuzz test above): a GIF header of 2048 x 33024 pixels, over
    MAX_TEXTURE_PIXELS and under PIL's own bomb limit, was refused without naming the file."""
    path = scratch("big.gif", b"GIF87a\x00\x00\x00\x00\x00\x00\x00,\x00\x00\x00\x00\x00\x08\x00\x81\x00\x00")
    with pytest.raises(SceneError, match="big.gif: 2048x33024 pixels exceeds the limit"):
        load_image(path)


def test_texture_decompression_bombs_and_corrupt_mesh_textures_are_scene_errors(tmp_path):
    """Regression: a PNG header claiming 20000 x 20000 pixels raised PIL's DecompressionBombError out of
    load_image, and an OBJ whose texture was truncated raised OSError out of load_mesh_file (PIL decodes lazily).
    Both are SceneErrors naming the file now; no pixels are allocated for the bomb."""
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(png(20_000, 20_000))
    tracemalloc.start()
    try:
        with pytest.raises(SceneError, match="bomb.png"):
            load_image(bomb)
        assert tracemalloc.get_traced_memory()[1] < 10**7
    finally:
        tracemalloc.stop()
    for name in ("fuze.obj", "fuze.obj.mtl"):
        (tmp_path / name).write_bytes((MESHES / name).read_bytes())
    (tmp_path / "fuze uv.jpg").write_bytes((MESHES / "fuze uv.jpg").read_bytes()[:20_000])
    with pytest.raises(SceneError, match="fuze.obj"):
        load_mesh_file(tmp_path / "fuze.obj")


def test_files_named_by_scenes_and_meshes_are_size_capped_and_regular(tmp_path):
    """A glTF buffer or a scene texture over the mesh size cap is refused by size (sparse: nothing read), and a
    texture that is a device (/dev/zero, size 0, endless) is refused as not a regular file. Regression: trimesh
    read whatever a mesh file named, whole, and /dev/zero as a texture was read without end."""
    sparse_buffer = tmp_path / "huge.bin"
    with sparse_buffer.open("wb") as f:
        f.truncate(MAX_MESH_BYTES + 1)
    gltf = {
        "asset": {"version": "2.0"},
        "buffers": [{"uri": "huge.bin", "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    }
    (tmp_path / "m.gltf").write_text(json.dumps(gltf))
    with pytest.raises(SceneError, match="larger than the limit"):
        load_mesh_file(tmp_path / "m.gltf")
    scene = tmp_path / "s.toml"
    for texture, message in (("/dev/zero", "not a regular file"), ("huge.bin", "larger than the limit")):
        scene.write_text(f'[materials.m]\ntexture = {{ kind = "image", image = "{texture}" }}\n')
        with pytest.raises(SceneError, match=message):
            load_scene_file(scene)
    scene.write_text('[materials.m]\ntexture = { kind = "image", image = "a\\u0000b.png" }\n')
    with pytest.raises(SceneError):
        load_scene_file(scene)


def test_trace_paths_with_a_nul_are_config_errors():
    """Regression: replay://a%00b.jsonl (a NUL after unquoting) raised ValueError out of load_trace; now a
    ConfigError."""
    with pytest.raises(ConfigError):
        load_trace("a\x00b.jsonl")
