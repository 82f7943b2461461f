"""Size limits (hmdrt.ranges): a scene, a resolution or an eval too large to fit is refused before any work starts,
in one line naming the key, the value, the limit and HMDRT_ALLOW_LARGE=1, which lifts the limits on purpose."""

from __future__ import annotations

import inspect
import time
import tracemalloc

import pytest

from hmdrt.cli import main
from hmdrt.compositor.config import load_config
from hmdrt.compositor.session import display_profile
from hmdrt.errors import ConfigError, SceneError
from hmdrt.evaluate.config import load_eval_config
from hmdrt.evaluate.groups import check_work
from hmdrt.optics import get_profile
from hmdrt.ranges import ALLOW_LARGE, MAX_EVAL_FRAMES, MAX_EYE_PIXELS, MAX_SCENE_TRIANGLES
from hmdrt.scene import check_scene, load_scene
from hmdrt.scene.builtin import TRIANGLES

from .helpers import DATA

CONFIGS = DATA.parents[1] / "configs"
LIFT = f"set {ALLOW_LARGE}=1 to allow it on purpose"
# one spec per size knob of each built-in scene, far past the triangle limit
TOO_LARGE = {
    ("voxel_city", "size"): "voxel_city?size=100000",
    ("tunnel_geom", "length"): "tunnel_geom?length=1000000.0",
    ("tunnel_geom", "detail"): "tunnel_geom?detail=1000",
    ("tunnel_maps", "length"): "tunnel_maps?length=10000000.0",
    ("tunnel_maps", "section"): "tunnel_maps?length=100000.0&section=0.1",
}


@pytest.fixture(autouse=True)
def limits_in_force(monkeypatch):
    monkeypatch.delenv(ALLOW_LARGE, raising=False)


def test_every_size_knob_of_every_built_in_scene_is_covered_here():
    knobs = {(scene, knob) for scene, estimate in TRIANGLES.items() for knob in inspect.signature(estimate).parameters}
    assert knobs == set(TOO_LARGE)


@pytest.mark.parametrize("spec", TOO_LARGE.values())
def test_a_scene_too_large_is_refused_at_once_without_allocating(spec):
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(SceneError) as refused:
            load_scene(spec)
        seconds = time.perf_counter() - t0
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    message = str(refused.value)
    assert seconds < 0.5 and peak < 1_000_000
    assert spec.split("?")[1].split("&")[-1] in message  # the knob and its value
    assert f"more than the limit of {MAX_SCENE_TRIANGLES:,}" in message and LIFT in message
    assert "\n" not in message


def test_voxel_city_names_its_size_and_the_triangles_it_would_make():
    with pytest.raises(SceneError, match=r"^scene 'voxel_city' with size=100000 makes about 4,080,000,000,000 tri"):
        check_scene("voxel_city?size=100000")


def test_a_size_knob_below_its_least_value_is_refused_not_clamped():
    for spec, message in [
        ("voxel_city?size=-3", "option size=-3 is outside [1, inf]"),
        ("tunnel_maps?section=0", "option section=0.0 is outside [0.1, inf]"),
        ("tunnel_geom?detail=0", "option detail=0 is outside [1, inf]"),
    ]:
        with pytest.raises(SceneError, match=message.replace("[", r"\[").replace("]", r"\]")):
            load_scene(spec)


def test_a_scene_file_of_too_many_triangles_is_refused_before_any_object_is_built(tmp_path):
    sphere = '[[objects]]\nkind = "sphere"\ncenter = [0, 0, -3]\nradius = 1\nmaterial = "m"\nsubdivisions = 7\n'
    path = tmp_path / "spheres.toml"
    path.write_text("[materials.m]\n" + sphere * 40)  # 40 x 327,680 triangles
    t0 = time.perf_counter()
    with pytest.raises(SceneError, match=rf"scene file {path} with 40 objects makes 13,107,200 triangles, .*{LIFT}"):
        load_scene(str(path))
    assert time.perf_counter() - t0 < 0.5


def test_a_mesh_file_past_the_limit_is_refused_once_its_triangles_are_known(monkeypatch):
    loaded = load_scene(str(DATA / "meshes" / "fuze.obj")).meshes[0]
    monkeypatch.setattr("hmdrt.scene.files.MAX_SCENE_TRIANGLES", len(loaded.faces) - 1)
    with pytest.raises(SceneError, match=rf"mesh file .*fuze.obj has {len(loaded.faces):,} triangles, more than"):
        load_scene(str(DATA / "meshes" / "fuze.obj"))


def test_the_override_admits_a_moderately_large_scene_without_building_it(monkeypatch):
    spec = "voxel_city?size=200"  # about 16.3M triangles
    with pytest.raises(SceneError, match="size=200 makes about 16,320,000 triangles"):
        check_scene(spec)
    monkeypatch.setenv(ALLOW_LARGE, "1")
    check_scene(spec)
    monkeypatch.setenv(ALLOW_LARGE, "yes")  # only 1 lifts the limits
    with pytest.raises(SceneError):
        check_scene(spec)


RESOLUTION = "20000x20000 has 400,000,000 pixels per eye, more than the limit of 16,777,216"


def test_a_20000x20000_run_config_display_is_refused_before_the_session_makes_buffers(tmp_path):
    path = tmp_path / "run.toml"
    path.write_text('[display]\nprofile = "sim-cpu"\nresolution = "20000x20000"\n')
    with pytest.raises(ConfigError, match=f"^display.resolution {RESOLUTION}; {LIFT}$"):
        display_profile(load_config(path))


def test_a_20000x20000_profile_file_is_refused(tmp_path):
    path = tmp_path / "huge.toml"
    text = (CONFIGS / "profiles" / "quest2_like.toml").read_text()
    path.write_text(text.replace("width = 1832", "width = 20000").replace("height = 1920", "height = 20000"))
    with pytest.raises(ConfigError, match=f"^profile {path}: width x height {RESOLUTION}; {LIFT}$"):
        get_profile(str(path))


def test_a_20000x20000_eval_resolution_is_refused_at_load(tmp_path):
    path = tmp_path / "e.toml"
    path.write_text('resolution = "20000x20000"\n')
    with pytest.raises(ConfigError, match=f"^resolution {RESOLUTION}; {LIFT}$"):
        load_eval_config(path)


def test_a_20000x20000_render_is_refused_in_one_line(tmp_path, capsys):
    out = tmp_path / "o.png"
    args = ["render", "--scene", "whitted", "--profile", "sim-cpu", "--method", "full", "--out", str(out)]
    assert main([*args, "--resolution", "20000x20000"]) == 1
    assert capsys.readouterr().err == f"hmdrt: error: --resolution {RESOLUTION}; {LIFT}\n"
    assert not out.exists()


def test_the_override_admits_a_moderately_large_resolution(monkeypatch):
    profile = get_profile("rift_s")
    with pytest.raises(ConfigError, match="resolution 5000x5000 has 25,000,000 pixels per eye"):
        profile.with_resolution_text("5000x5000")
    assert profile.with_resolution_text("4096x4096").width * 4096 == MAX_EYE_PIXELS  # the limit itself is allowed
    monkeypatch.setenv(ALLOW_LARGE, "1")
    assert (profile.with_resolution_text("5000x5000").width, profile.with_resolution_text("5000x5000").height) == (
        5000,
        5000,
    )


def eval_text(scenes: int, traces: int, cells: int, frames: int) -> str:
    """An eval config of `scenes` x `traces` x `cells` (regular at 1.. spp) x `frames` frames on one profile, in one
    timing round."""
    return "\n".join(
        [
            f"scenes = {[f'whitted?ao_distance={i + 1}' for i in range(scenes)]}",
            f"frames = {frames}",
            "timing_rounds = 1",
            *(f'[[traces]]\ngaze = "{i % 80},0"\nname = "t{i}"' for i in range(traces)),
            f'[[methods]]\nname = "regular"\nsweep = {{ spp = {list(range(1, cells + 1))} }}',
        ]
    )


def test_an_eval_of_5e10_frames_is_refused_at_load_with_the_count_and_the_limit(tmp_path):
    path = tmp_path / "huge.toml"
    path.write_text(eval_text(scenes=50, traces=100, cells=100, frames=100_000))
    t0 = time.perf_counter()
    with pytest.raises(ConfigError) as refused:
        load_eval_config(path)
    assert str(refused.value) == (
        "the eval renders 50,000,000,000 frames (scenes x profiles x traces x method cells x frames x timing rounds), "
        f"more than the limit of {MAX_EVAL_FRAMES:,}; {LIFT}"
    )
    assert time.perf_counter() - t0 < 2.0


def test_the_override_admits_a_moderately_large_eval_at_load(tmp_path, monkeypatch):
    path = tmp_path / "big.toml"
    path.write_text(eval_text(scenes=1, traces=2, cells=10, frames=100_000))  # 2,000,000 frames
    with pytest.raises(ConfigError, match="renders 2,000,000 frames"):
        load_eval_config(path)
    monkeypatch.setenv(ALLOW_LARGE, "1")
    assert load_eval_config(path).frames == 100_000


def test_an_eval_scene_too_large_is_refused_at_load(tmp_path):
    path = tmp_path / "e.toml"
    path.write_text('scenes = ["whitted", "voxel_city?size=100000"]\n')
    with pytest.raises(SceneError, match=f"^scene 'voxel_city' with size=100000 .*; {LIFT}$"):
        load_eval_config(path)


def test_the_shipped_configs_and_profiles_are_within_the_limits():
    for path in sorted((CONFIGS / "eval").glob("*.toml")):
        check_work(load_eval_config(path))
    for path in [*CONFIGS.glob("*.toml"), *(CONFIGS / "bench").glob("*.toml")]:
        config = load_config(path)
        display_profile(config)
        check_scene(config.scene)
    for path in (CONFIGS / "profiles").glob("*.toml"):
        get_profile(str(path))


def test_each_trace_of_a_sweep_counts_in_the_evals_frames(tmp_path):
    path = tmp_path / "swept.toml"
    text = eval_text(scenes=1, traces=1, cells=4, frames=100_000)
    path.write_text(text.replace('name = "t0"', "sweep = { latency_ms = [0, 10, 20] }"))  # 3 traces x 4 cells
    with pytest.raises(ConfigError, match="the eval renders 1,200,000 frames"):
        load_eval_config(path)
