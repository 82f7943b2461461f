"""Built-in scenes, TOML scene descriptions and mesh files: they load, and render without NaN."""

from pathlib import Path

import msgspec
import numpy as np
import pytest

from hmdrt.errors import SceneError
from hmdrt.optics import get_profile
from hmdrt.scene import BUILTINS, load_scene
from hmdrt.scene.builtin import voxel_city
from hmdrt.scene.model import Image, Noise
from hmdrt.scene.pack import pack

from .helpers import DATA, render


@pytest.mark.parametrize("name", sorted(BUILTINS))
def test_builtin_scene_renders_finite_and_not_blank(name):
    image, stats = render(name, 40, 45)
    assert image.shape == (45, 40, 3)
    assert np.all(np.isfinite(image)) and image.min() >= 0
    assert image.std() > 0.01  # something is in view
    assert stats.rays["primary"] == 40 * 45


def test_builtin_scenes_have_the_papers_content():
    whitted = load_scene("whitted")
    mats = {m.name: whitted.materials[m.material] for m in whitted.meshes}
    assert mats["mirror_sphere"].reflectance > 0.5 and mats["glass_sphere"].transmittance > 0.5
    assert whitted.materials["floor"].texture is not None and len(whitted.lights) == 1
    assert not load_scene("tunnel_maps").has_secondary  # no mirrors: primary and shadow rays only
    assert 150_000 <= load_scene("shooting_range").triangle_count <= 250_000
    interior = load_scene("interior")
    assert interior.ao_samples > 0 and any(type(l).__name__ == "AreaLight" for l in interior.lights)
    assert load_scene("bunny").meshes[0].faces.shape == (16301, 3)


def test_voxel_city_size_knob_reaches_a_million_triangles():
    assert voxel_city(size=8).triangle_count < voxel_city(size=16).triangle_count
    assert load_scene("voxel_city?size=50").triangle_count >= 1_000_000


def test_scene_options_apply_to_any_scene():
    s = load_scene("interior?max_depth=1&ao_samples=4&area_samples=2")
    assert (s.max_depth, s.ao_samples, s.lights[0].samples) == (1, 4, 2)
    with pytest.raises(SceneError, match="has no option 'sizee'"):
        load_scene("voxel_city?sizee=3")
    with pytest.raises(SceneError, match="not a valid int"):
        load_scene("voxel_city?size=big")
    with pytest.raises(SceneError, match="outside"):
        load_scene("whitted?max_depth=99")


def test_unknown_scene_names_the_choices():
    with pytest.raises(SceneError, match="built-in scenes: whitted"):
        load_scene("whitted2")


def test_textured_obj_loads_with_its_material_and_texture():
    scene = load_scene(str(DATA / "meshes" / "fuze.obj"))
    textured = [m for m in scene.materials.values() if isinstance(m.texture, Image)]
    assert len(textured) == 1 and len(scene.images) == 1
    img = next(iter(scene.images.values()))
    assert img.shape == (1024, 1024, 3) and img.dtype == np.float32 and 0 <= img.min() and img.max() <= 1
    mesh = scene.meshes[0]
    assert mesh.uv is not None and len(mesh.uv) == len(mesh.vertices)
    image, _ = render(scene, 48, 48)
    assert np.all(np.isfinite(image))


def test_textured_glb_loads_all_meshes_with_transforms():
    scene = load_scene(str(DATA / "meshes" / "CesiumMilkTruck.glb"))
    truck = [m for m in scene.meshes if m.name != "floor"]
    assert sum(len(m.faces) for m in truck) == 3624 and len(truck) == 5
    lo = np.min([m.vertices.min(0) for m in truck], 0)
    assert abs(lo[1]) < 1e-9  # placed on the floor
    image, _ = render(scene, 48, 48)
    assert np.all(np.isfinite(image)) and image.std() > 0.02


SCENE_TOML = """
name = "demo"
background = [0.3, 0.4, 0.5]
ambient = [0.1, 0.1, 0.1]
max_depth = 2

[camera]
position = [0.0, 1.0, 3.0]
look_at = [0.0, 0.5, 0.0]

[materials.red]
diffuse = [0.8, 0.1, 0.1]

[materials.floor]
diffuse = [1.0, 1.0, 1.0]
texture = { kind = "checker", scale = 2.0 }

[materials.glass]
transmittance = 0.9
ior = 1.5
diffuse = [0.0, 0.0, 0.0]

[[objects]]
kind = "quad"
corner = [-5.0, 0.0, 5.0]
edge_u = [10.0, 0.0, 0.0]
edge_v = [0.0, 0.0, -10.0]
material = "floor"
uv_scale = [10.0, 10.0]

[[objects]]
kind = "sphere"
center = [0.6, 0.5, 0.0]
radius = 0.5
material = "glass"

[[objects]]
kind = "box"
lo = [-1.2, 0.0, -0.5]
hi = [-0.4, 0.8, 0.3]
material = "red"

[[objects]]
kind = "mesh"
path = "MESH"
scale = 3.0
translate = [0.0, 0.0, -1.0]
rotate_deg = [-90.0, 0.0, 0.0]

[[lights]]
kind = "point"
position = [2.0, 4.0, 3.0]
intensity = [20.0, 20.0, 20.0]

[[lights]]
kind = "area"
corner = [-1.0, 3.0, -1.0]
edge_u = [2.0, 0.0, 0.0]
edge_v = [0.0, 0.0, 2.0]
radiance = [2.0, 2.0, 2.0]
samples = 4
"""


def test_toml_scene_description_builds_and_renders(tmp_path):
    f = tmp_path / "demo.toml"
    f.write_text(SCENE_TOML.replace("MESH", str(DATA / "meshes" / "fuze.obj")))
    scene = load_scene(str(f))
    assert scene.name == "demo" and scene.max_depth == 2 and len(scene.lights) == 2
    assert scene.triangle_count > 1000 and scene.has_secondary
    image, stats = render(scene, 40, 40)
    assert np.all(np.isfinite(image)) and stats.rays["area"] > 0 and stats.rays["secondary"] > 0


@pytest.mark.parametrize(
    "edit,message",
    [
        (lambda t: t + "\n[oops\n", "not valid TOML"),
        (lambda t: t.replace('name = "demo"', 'name = "demo"\ncolour = 3'), "unknown field `colour`"),
        (lambda t: t.replace("radius = 0.5", "radius = -0.5"), "radius"),
        (lambda t: t.replace("transmittance = 0.9", "transmittance = 0.9\nreflectance = 0.5"), "must not exceed 1"),
        (lambda t: t.replace('material = "red"', 'material = "blue"'), "unknown material 'blue'"),
        (lambda t: t.replace("MESH", "missing.obj"), "mesh file not found"),
        (lambda t: t.replace('kind = "point"', 'kind = "spot"'), "spot"),
    ],
)
def test_bad_scene_files_give_clear_errors(tmp_path, edit, message):
    f = tmp_path / "bad.toml"
    f.write_text(edit(SCENE_TOML).replace("MESH", str(DATA / "meshes" / "fuze.obj")))
    with pytest.raises(SceneError, match=message):
        pack(load_scene(str(f)))


def test_corrupt_and_missing_mesh_files(tmp_path):
    with pytest.raises(SceneError, match="not found"):
        load_scene(str(tmp_path / "nothing.obj"))
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"glTF\x02\x00\x00\x00garbage")
    with pytest.raises(SceneError, match="cannot load mesh file"):
        load_scene(str(bad))
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(SceneError):
        load_scene(str(empty))


CONFIGS = Path(__file__).parents[1] / "configs"


@pytest.mark.parametrize("path", sorted((CONFIGS / "scenes").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_scene_configs_load_and_pack(path):
    scene = load_scene(str(path))
    assert scene.triangle_count > 0
    pack(scene)


@pytest.mark.parametrize("path", sorted((CONFIGS / "profiles").glob("*.toml")), ids=lambda p: p.name)
def test_shipped_profile_configs_load(path):
    assert get_profile(str(path)).width > 0


@pytest.mark.parametrize("octaves", [0, 13])
def test_a_noise_texture_made_in_python_past_its_octave_bound_is_refused(octaves):
    """Scene files are validated as they are read; a Noise made in Python is not, and pack refuses what the texture
    kernels hold no table for, where the lookup would read past it."""
    scene = load_scene("interior")
    floor = scene.materials["floor"]
    scene.materials["floor"] = msgspec.structs.replace(floor, texture=Noise(octaves=octaves))
    with pytest.raises(SceneError, match=f"{octaves} octaves; 1 to 12"):
        pack(scene)
