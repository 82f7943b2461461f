"""The `hmdrt render` command line, run as a user runs it: PNG + stats JSON, and one-line errors."""

import json
import subprocess
import sys

import numpy as np
import pytest
from PIL import Image

from .helpers import DATA

RENDER_KEYS = {"ms_total", "stages_ms", "rays", "width", "height", "method", "scene", "stages_run"}
RAY_KEYS = {"primary", "shadow", "secondary", "ao", "area", "total"}


def hmdrt(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "hmdrt", *args], capture_output=True, text=True, cwd=cwd, timeout=300)


def test_render_writes_png_and_stats_with_the_design_keys(tmp_path):
    out, stats = tmp_path / "w.png", tmp_path / "w.json"
    r = hmdrt(
        *"render --scene whitted --profile sim-cpu --method full --resolution 64x48 --out".split(),
        str(out),
        "--stats",
        str(stats),
    )
    assert r.returncode == 0, r.stderr
    img = np.asarray(Image.open(out))
    assert img.shape == (48, 64, 3) and img.std() > 10
    record = json.loads(stats.read_text())
    assert RENDER_KEYS <= set(record) and RAY_KEYS == set(record["rays"])
    assert (record["width"], record["height"], record["method"], record["scene"]) == (64, 48, "full", "whitted")
    assert record["rays"]["primary"] == 64 * 48
    assert record["rays"]["total"] == sum(v for k, v in record["rays"].items() if k != "total")
    assert record["stages_run"] == list(record["stages_ms"])
    assert {"primary", "shadow", "secondary", "present"} <= set(record["stages_run"])
    assert record["ms_total"] >= sum(record["stages_ms"].values()) * 0.95
    assert str(out) in r.stdout


def test_regular_takes_spp_and_both_eyes_go_side_by_side(tmp_path):
    out, stats = tmp_path / "r.png", tmp_path / "r.json"
    r = hmdrt(
        *"render --scene whitted --profile sim-cpu --method regular --spp 4 --resolution 24x20 --eye both".split(),
        "--out",
        str(out),
        "--stats",
        str(stats),
    )
    assert r.returncode == 0, r.stderr
    record = json.loads(stats.read_text())
    assert (record["width"], record["height"], record["spp"]) == (48, 20, 4)
    assert record["rays"]["primary"] == 2 * 24 * 20 * 4
    assert "resolve" in record["stages_run"]


@pytest.mark.parametrize(
    "args,message",
    [
        (["--scene", "nowhere"], "unknown scene 'nowhere'"),
        (["--scene", "MALFORMED"], "not valid TOML"),
        (["--scene", "MISSING_MESH"], "mesh file not found"),
        (["--scene", "missing.obj"], "mesh file not found"),
        (["--resolution", "0x0"], "at least 1x1"),
        (["--resolution", "wide"], "WIDTHxHEIGHT"),
        (["--profile", "oculus_quest_9"], "unknown profile"),
        (["--method", "magic"], "unknown method 'magic'"),
        (["--method", "regular?spp=zero"], "Expected `int`"),
        (["--frames", "0"], "argument --frames: must be at least 1, got 0"),
        (["--threads", "x"], "argument --threads: not a whole number: 'x'"),
        (["--frames", "2", "--trace", "missing.jsonl"], "trace not found"),
        (["--gaze", "nan,0"], "gaze angles must be finite"),
        (["--spp", "4"], "--spp applies to method regular"),
        (["--out", "/proc/forbidden/x.png"], "cannot write"),
    ],
)
def test_bad_input_gives_one_clear_line_and_a_nonzero_exit(tmp_path, args, message):
    (tmp_path / "malformed.toml").write_text('name = "x"\n[camera\n')
    (tmp_path / "missing_mesh.toml").write_text('[[objects]]\nkind = "mesh"\npath = "gone.glb"\n')
    base = {
        "--scene": "whitted",
        "--profile": "sim-cpu",
        "--method": "full",
        "--resolution": "8x8",
        "--out": str(tmp_path / "o.png"),
    }
    for flag, value in zip(args[::2], args[1::2], strict=True):
        base[flag] = value.replace("MALFORMED", str(tmp_path / "malformed.toml")).replace(
            "MISSING_MESH", str(tmp_path / "missing_mesh.toml")
        )
    r = hmdrt("render", *[x for kv in base.items() for x in kv], cwd=tmp_path)
    assert r.returncode != 0
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1, r.stderr
    assert message in lines[0] and "Traceback" not in r.stderr
    assert not (tmp_path / "o.png").exists()


def test_mesh_file_scene_from_the_command_line(tmp_path):
    r = hmdrt(
        "render",
        "--scene",
        str(DATA / "meshes" / "CesiumMilkTruck.glb"),
        "--profile",
        "rift_s",
        "--method",
        "full",
        "--resolution",
        "32x36",
        "--out",
        str(tmp_path / "t.png"),
    )
    assert r.returncode == 0, r.stderr


def test_the_console_script_and_python_m_hmdrt_reach_the_same_main():
    from importlib.metadata import entry_points

    from hmdrt import cli

    (script,) = [e for e in entry_points(group="console_scripts") if e.name == "hmdrt"]
    assert script.value == "hmdrt.cli:main" and script.load() is cli.main
    r = hmdrt("--version")
    assert r.returncode == 0 and r.stdout.startswith("hmdrt "), r.stderr


def _eccentricity(width: int, height: int, yaw: float, pitch: float) -> np.ndarray:
    """Each pixel's angle from the gaze (degrees) in sim-cpu's left eye at this resolution, looking from the start."""
    from hmdrt.optics import get_profile
    from hmdrt.scene import load_scene
    from hmdrt.spatial import gaze_direction
    from hmdrt.views import eye_cameras

    profile = get_profile("sim-cpu").with_resolution(width, height)
    camera = eye_cameras(profile, load_scene("whitted").start, ("left",))["left"]
    return camera.eccentricity(np.array(gaze_direction(yaw, pitch)))


def test_a_temporal_methods_single_frame_is_its_steady_image_after_its_declared_warm_up(tmp_path, capsys):
    """One frame of rrm (the default method) is what it shows once its refresh cycle has passed: on a still view
    its fovea and periphery equal full's, where without the warm-up most of its periphery is still black. A
    negative gaze after --gaze reads as the gaze."""
    from hmdrt.cli import main

    common = "render --scene whitted --profile sim-cpu --resolution 96x108 --gaze -10,5".split()
    images = {}
    for name, extra in (("rrm", []), ("full", []), ("cold", ["--warmup", "0"])):
        method = "full" if name == "full" else "rrm"
        assert main([*common, "--method", method, "--out", str(tmp_path / f"{name}.png"), *extra]) == 0
        images[name] = np.asarray(Image.open(tmp_path / f"{name}.png")).astype(float)
    printed = capsys.readouterr().out
    assert "after 12 warm-up frames of the same view (rrm's history)" in printed  # group 4 x 3
    eccentricity = _eccentricity(96, 108, -10.0, 5.0)
    fovea, periphery = eccentricity <= 10.0, eccentricity > 20.0
    assert fovea.sum() > 100 and periphery.sum() > 1000  # the gaze is where -10,5 puts it
    difference = np.abs(images["rrm"] - images["full"]).mean(axis=2)
    assert difference[fovea].mean() < 1.0 and difference[periphery].mean() < 1.0  # 8-bit levels
    black = (images["cold"].max(axis=2) == 0)[periphery].mean()
    assert black > 0.5, f"one cold rrm frame leaves {black:.0%} of the periphery black"
