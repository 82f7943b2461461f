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
