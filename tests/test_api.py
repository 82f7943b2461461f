"""hmdrt as a library (hmdrt.api): the G-buffer against known geometry, the compositor's report, traces converted
and read back, and every example of docs/api.md run as it is, its results checked."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from hmdrt import api
from hmdrt.compositor.config import load_config
from hmdrt.errors import SceneError
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import Scene
from hmdrt.scene.model import Material, PointLight
from hmdrt.scene.pack import pack
from hmdrt.scene.shapes import quad, sphere
from hmdrt.spatial import Pose, gaze_direction
from hmdrt.telemetry.view import Report
from hmdrt.testing import write_config

DOCS = Path(__file__).resolve().parent.parent / "docs" / "api.md"
EYE_HEIGHT = 1.5
CENTRE, RADIUS = np.array([0.3, 1.0, -4.0]), 0.5
BACKGROUND = (0.2, 0.3, 0.4)


def floor_and_ball() -> Scene:
    """A floor at y = 0 (meshes[0], two triangles) and a ball (meshes[1]) ahead of an eye 1.5 m up, looking down."""
    floor = quad("floor", (-20, 0, 20), (40, 0, 0), (0, 0, -40), "grey")
    ball = sphere("ball", CENTRE, RADIUS, "grey", subdivisions=5)
    light = PointLight(position=(2.0, 5.0, 0.0), intensity=(20.0,) * 3)
    grey = {"grey": Material(diffuse=(0.5, 0.5, 0.5))}
    start = Pose.looking((0.0, EYE_HEIGHT, 0.0), 0.0, -15.0)
    return Scene("floor_and_ball", [floor, ball], grey, [light], background=BACKGROUND, start=start)


@pytest.fixture(scope="module")
def frame() -> api.RenderedFrame:
    return api.render_frame(floor_and_ball(), "sim-cpu", "full", (0.0, 0.0), resolution=(48, 54))


def test_the_gbuffer_holds_the_floors_and_the_balls_hits_where_geometry_puts_them(frame):
    g = frame.gbuffer
    assert frame.image.shape == (54, 48, 3) and g.depth.shape == (54, 48) and g.position.shape == (54, 48, 3)
    floor, ball, miss = g.object_id == 0, g.object_id == 1, g.object_id == -1
    assert floor.sum() > 500 and ball.sum() > 20 and miss.sum() > 100  # each is in view
    np.testing.assert_allclose(g.origin, [-0.0635 / 2, EYE_HEIGHT, 0.0])  # the left eye, half the IPD to the left

    # the floor at y = 0: a ray from 1.5 m up meets it after 1.5 / -dy metres, facing up
    np.testing.assert_allclose(g.depth[floor], EYE_HEIGHT / -g.direction[floor][:, 1], rtol=1e-5)
    np.testing.assert_allclose(g.position[floor][:, 1], 0.0, atol=1e-4)
    np.testing.assert_allclose(g.normal[floor], np.tile([0.0, 1.0, 0.0], (floor.sum(), 1)), atol=1e-6)
    # the ball: hits on its tessellated surface, within the tessellation of the sphere's radius
    distance = np.linalg.norm(g.position[ball] - CENTRE, axis=1)
    assert np.all(distance <= RADIUS + 1e-4) and np.all(distance >= 0.999 * RADIUS)
    # position = origin + depth * direction everywhere, and the directions are unit
    hit = ~miss
    np.testing.assert_allclose(g.position[hit], g.origin + g.depth[hit, None] * g.direction[hit], atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(g.direction, axis=2), 1.0, rtol=1e-6)

    # triangles: the floor's are 0 and 1, the ball's follow; each belongs to the object recorded
    tri_object = pack(floor_and_ball()).geometry.tri_object
    assert set(np.unique(g.triangle_id[floor])) <= {0, 1} and np.all(g.triangle_id[ball] >= 2)
    np.testing.assert_array_equal(tri_object[g.triangle_id[hit]], g.object_id[hit])
    # misses: no hit anywhere, and the image shows the background there
    assert np.all(np.isinf(g.depth[miss])) and np.all(g.triangle_id[miss] == -1) and np.isnan(g.position[miss]).all()
    np.testing.assert_allclose(frame.image[miss], np.tile(BACKGROUND, (miss.sum(), 1)), rtol=1e-6)
    assert frame.stats.rays["primary"] == 48 * 54 and frame.method == "full"


def test_trace_gbuffer_gives_the_tracers_own_hits_at_the_samples_asked(frame):
    xy = pixel_centres(48, 54)[[0, 48 * 40 + 20, 48 * 54 - 1]]
    rgb, gbuf, stats = api.trace_gbuffer(floor_and_ball(), frame.camera, xy)
    column, row = xy[:, 0].astype(int), xy[:, 1].astype(int)
    np.testing.assert_array_equal(gbuf.primary.depth, frame.gbuffer.depth[row, column])
    np.testing.assert_array_equal(gbuf.primary.object_id, frame.gbuffer.object_id[row, column])
    assert rgb.shape == (3, 3) and stats.rays["primary"] == 3


def test_the_gaze_the_eye_and_the_method_reach_the_frame():
    scene = floor_and_ball()
    left = api.render_frame(scene, "sim-cpu", "rrm?fovea_deg=5", (10.0, -5.0), resolution=(32, 36), gbuffer=False)
    assert left.gbuffer is None and left.method == "rrm?fovea_deg=5.0" and left.image.shape == (36, 32, 3)
    np.testing.assert_allclose(left.gaze, gaze_direction(10.0, -5.0))
    right = api.render_frame(scene, resolution=(32, 36), gaze=(0.0, 0.0, -2.0), eye="right", gbuffer=False)
    np.testing.assert_allclose(right.gaze, [0.0, 0.0, -1.0])
    np.testing.assert_allclose(right.camera.position - left.camera.position, [0.0635, 0.0, 0.0], atol=1e-9)
    for bad in [(0.0, 0.0, 0.0), (1.0, 2.0, 3.0, 4.0), (np.nan, 0.0)]:
        with pytest.raises(ValueError, match="gaze"):
            api.render_frame(scene, gaze=bad, resolution=(8, 8))
    with pytest.raises(SceneError):
        api.render_frame("nosuch", resolution=(8, 8))


def test_run_compositor_runs_a_loaded_config_for_n_frames_in_virtual_time(tmp_path):
    config = load_config(write_config(tmp_path / "run.toml", eyes="left"))
    report = api.run_compositor(config, frames=5, seed=3)
    assert isinstance(report, Report) and report.vsyncs == report["vsyncs"] == 5
    assert report.frames == 5 and report.deadline_misses == 0 and report.virtual_time is True and report.seed == 3
    assert report.period_ms == pytest.approx(1000 / 30) and report.display.eyes == ["left"]
    assert report.drivers.replay.samples > 0  # hmdrt.testing.TRACE, replayed
    assert json.loads(json.dumps(report.to_dict())) == report
    with pytest.raises(ValueError, match="frames"):
        api.run_compositor(config, frames=0)


def test_import_hmdrt_loads_no_kernels_until_the_api_is_used():
    code = (
        "import sys, hmdrt\n"
        "assert not {'numba', 'numpy', 'hmdrt.api'} & set(sys.modules), sorted(sys.modules)\n"
        "assert hmdrt.render_frame is __import__('hmdrt.api').api.render_frame\n"
        "print(hmdrt.__version__)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "0.1.0", out.stderr


def examples() -> list[str]:
    return re.findall(r"```python\n(.*?)```", DOCS.read_text(), re.S)


def test_the_docs_examples_run_as_written(tmp_path, monkeypatch):
    """docs/api.md's four examples, each in a namespace of its own in an empty folder, as a reader would."""
    monkeypatch.chdir(tmp_path)
    render, trace, run, convert = examples()

    ns: dict = {}
    exec(render, ns)
    assert ns["frame"].image.shape == (108, 96, 3) and ns["frame"].method == "rrm?fovea_deg=5.0"
    assert 0.3 < ns["hit"].mean() < 0.9
    np.testing.assert_allclose(ns["frame"].gaze, gaze_direction(10.0, -5.0))

    ns = {}
    exec(trace, ns)
    depth, objects = ns["gbuf"].primary.depth, ns["gbuf"].primary.object_id
    assert ns["stats"].rays["primary"] == 2 and ns["scene"].meshes[objects[1]].name == "floor"
    bottom = ns["camera"].directions(ns["xy"])[1]
    assert depth[1] == pytest.approx(ns["scene"].start.position[1] / -bottom[1], rel=1e-5)

    ns = {}
    exec(run, ns)
    report = ns["report"]
    assert report.vsyncs == 30 and report.deadline_misses == 0 and report.drivers.synthetic.samples > 0
    assert 0 < report.latency_ms.gaze_to_photon.p50 <= report.latency_ms.gaze_to_photon.p99

    ns = {}
    exec(convert, ns)
    native = ns["native"]
    assert native.device == "lab" and native.malformed == 0
    assert [(s.t_host, s.valid) for s in native.samples] == [(0, True), (4_000_000, True), (8_000_000, False)]
    np.testing.assert_allclose(native.samples[1].C, gaze_direction(1.5, -2.0))
