"""Traces, sequences and the sequence command line."""

import json

import numpy as np
import pytest

from hmdrt.cli import main
from hmdrt.errors import ConfigError
from hmdrt.foveation import METHODS
from hmdrt.replay.trace import Gaze, read_trace, write_trace
from hmdrt.replay.trace import Pose as PoseSample
from hmdrt.scene import BUILTINS
from hmdrt.spatial import Pose, gaze_direction, quat_from_yaw_pitch, quat_rotate, quat_to_matrix, unit
from hmdrt.views import builtin_path, compose_pose, from_trace

MS = 1_000_000


def gaze(seq, t_ms, yaw=0.0, pitch=0.0, valid=True, **kw):
    return Gaze(seq=seq, t_host=int(t_ms * MS), valid=valid, C=tuple(gaze_direction(yaw, pitch)), **kw)


def test_trace_round_trip_including_gzip(tmp_path):
    samples = [
        gaze(0, 0.0, 3.0, -2.0, depth_m=1.5),
        gaze(1, 4.0, valid=False),
        PoseSample(seq=0, t_host=0, position=(0.0, 0.1, 0.0), orientation=(1.0, 0.0, 0.0, 0.0)),
        Gaze(seq=2, t_host=8 * MS, L=(0.0, 0.0, -1.0), R=(0.0, 0.0, -1.0)),
    ]
    for name in ("t.jsonl", "t.jsonl.gz"):
        write_trace(tmp_path / name, samples, device="unit")
        back = read_trace(tmp_path / name)
        assert back.device == "unit" and back.samples == samples and back.malformed == 0


def test_malformed_lines_are_counted_not_fatal(tmp_path):
    path = tmp_path / "bad.jsonl"
    write_trace(path, [gaze(0, 0.0), gaze(1, 10.0)])
    with path.open("a") as f:
        f.write("not json\n")
        f.write('{"kind": "gaze", "seq": -1, "t_host": 0, "C": [0, 0, -1]}\n')  # negative seq
        f.write('{"kind": "teleport", "seq": 3, "t_host": 0}\n')
        f.write("x" * 70_000 + "\n")  # longer than the line cap
        f.write(json.dumps({"kind": "gaze", "seq": 4, "t_host": 20 * MS, "C": [0.0, 0.0, -1.0]}) + "\n")
    reading = read_trace(path)
    assert reading.malformed == 4 and len(reading.samples) == 3


@pytest.mark.parametrize(
    "content,message",
    [
        ("", "not an hmdrt-trace file"),
        ('{"format": "csv", "v": 1}\n', "not an hmdrt-trace file"),
        ('{"format": "hmdrt-trace", "v": 9}\n', "version 9"),
    ],
)
def test_bad_headers_are_refused(tmp_path, content, message):
    path = tmp_path / "t.jsonl"
    path.write_text(content)
    with pytest.raises(ConfigError, match=message):
        read_trace(path)


def test_frames_take_the_latest_valid_gaze_and_hold_it_through_blinks(tmp_path):
    path = tmp_path / "t.jsonl"
    samples = [
        gaze(0, 0.0, 0.0),
        gaze(1, 10.0, 5.0),
        gaze(2, 20.0, valid=False),
        gaze(3, 30.0, valid=False),
        gaze(4, 40.0, -7.0),
        Gaze(seq=5, t_host=50 * MS, C=(0.0, 0.6, -0.6)),
    ]  # not a unit vector
    write_trace(path, samples)
    period = 10 * MS
    inputs, counts = from_trace(read_trace(path), 6, period, Pose())
    yaws = [np.degrees(np.arctan2(i.gaze["left"][0], -i.gaze["left"][2])) for i in inputs]
    np.testing.assert_allclose(yaws, [0.0, 5.0, 5.0, 5.0, -7.0, -7.0], atol=1e-9)
    assert counts.gaze_invalid == 3 and counts.held_frames == 3


def test_trace_poses_are_relative_to_the_scene_start(tmp_path):
    path = tmp_path / "t.jsonl"
    turn = quat_from_yaw_pitch(10.0, 0.0)
    write_trace(path, [gaze(0, 0.0), PoseSample(seq=0, t_host=0, position=(0.0, 0.0, -1.0), orientation=tuple(turn))])
    start = Pose.looking((1.0, 1.6, 2.0), 90.0, 0.0)
    inp = from_trace(read_trace(path), 1, 10 * MS, start)[0][0]
    np.testing.assert_allclose(inp.pose.position, start.position + quat_to_matrix(start.orientation) @ [0, 0, -1])
    forward = quat_to_matrix(inp.pose.orientation) @ [0.0, 0.0, -1.0]
    np.testing.assert_allclose(forward, gaze_direction(100.0, 0.0), atol=1e-12)


def test_builtin_path_is_deterministic_and_has_fixations_and_saccades():
    a = builtin_path(60, 11_111_111, Pose(), seed=1)
    b = builtin_path(60, 11_111_111, Pose(), seed=1)
    gz = np.array([i.gaze["left"] for i in a])
    assert np.array_equal(gz, [i.gaze["left"] for i in b])
    steps = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", gz[1:], gz[:-1]), -1, 1)))
    assert (steps < 1e-3).sum() > 40 and (steps > 1.0).sum() >= 1  # mostly fixating, some saccades
    assert len({tuple(np.round(i.pose.orientation, 9)) for i in a}) > 50  # the head keeps moving


def test_sequence_command_writes_frames_and_per_frame_stats(tmp_path, capsys):
    trace = tmp_path / "t.jsonl"
    write_trace(trace, [gaze(k, 30.0 * k, 2.0 * k, 0.0) for k in range(10)])
    out = tmp_path / "seq"
    code = main(
        [
            *"render --scene whitted --profile sim-cpu --method weier16?frc=small --resolution 48x54 --trace".split(),
            str(trace),
            "--frames",
            "5",
            "--out",
            str(out),
            "--stats",
            str(tmp_path / "s.json"),
        ]
    )
    assert code == 0
    assert sorted(p.name for p in out.glob("*.png")) == [f"frame_{k:05d}.png" for k in range(5)]
    records = [json.loads(line) for line in (out / "frames.jsonl").read_text().splitlines()]
    assert [r["frame"] for r in records] == list(range(5)) and all(r["method"] == "weier16" for r in records)
    assert "reproject" not in records[0]["stages_run"] and "reproject" in records[1]["stages_run"]
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["frames"] == 5 and summary["trace"]["malformed_lines"] == 0
    assert {"ms_total", "stages_ms", "rays", "width", "height", "method", "scene", "stages_run"} <= set(summary)
    assert "5 frames" in capsys.readouterr().out


def test_builtin_trace_and_frames_default_from_the_trace(tmp_path):
    trace = tmp_path / "t.jsonl"
    write_trace(trace, [gaze(k, 50.0 * k) for k in range(4)])  # 150 ms at 30 Hz: 5 frames
    assert (
        main(
            [
                *"render --scene voxel_city?size=4 --profile sim-cpu --method rrm --resolution 32x36 --trace".split(),
                str(trace),
                "--out",
                str(tmp_path / "a"),
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "a").glob("*.png"))) == 5
    assert (
        main(
            [
                *"render --scene voxel_city?size=4 --profile sim-cpu --method rrm --resolution 32x36".split(),
                *"--trace builtin --frames 3 --out".split(),
                str(tmp_path / "b"),
            ]
        )
        == 0
    )
    assert len(list((tmp_path / "b").glob("*.png"))) == 3


@pytest.mark.parametrize("scene", sorted(BUILTINS))
@pytest.mark.parametrize("method", sorted(set(METHODS) - {"regular"}))
def test_every_method_renders_every_builtin_scene(tmp_path, scene, method):
    out = tmp_path / "f.png"
    assert (
        main(
            [
                "render",
                "--scene",
                scene,
                "--profile",
                "rift_s",
                "--method",
                method,
                "--resolution",
                "40x45",
                "--out",
                str(out),
                "--stats",
                str(tmp_path / "s.json"),
                "--eye",
                "both",
            ]
        )
        == 0
    )
    stats = json.loads((tmp_path / "s.json").read_text())
    assert stats["width"] == 80 and stats["method"] == method and stats["rays"]["primary"] > 0


def test_a_relative_pose_is_placed_at_the_start_pose():
    rng = np.random.default_rng(7)
    for _ in range(50):
        q, v = rng.normal(size=4), rng.normal(size=3)
        np.testing.assert_allclose(quat_rotate(q, v), quat_to_matrix(q) @ v, atol=1e-12)
        start = Pose(rng.normal(size=3), np.array(unit(q)))
        relative = PoseSample(seq=0, t_host=0, position=tuple(v), orientation=tuple(rng.normal(size=4)))
        head = compose_pose(start, relative)
        np.testing.assert_allclose(head.position, start.position + quat_to_matrix(q) @ v, atol=1e-12)
        np.testing.assert_allclose(
            quat_to_matrix(head.orientation), quat_to_matrix(q) @ quat_to_matrix(relative.orientation), atol=1e-12
        )
