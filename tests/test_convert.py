"""hmdrt convert: every format hmdrt reads to native JSONL and hmdrt CSV and back, and the BIDS eye-tracking export."""

from __future__ import annotations

import gzip
import importlib.util
import json
import subprocess
import sys
from decimal import Decimal
from pathlib import Path

import pytest

from hmdrt import cli
from hmdrt.bus.messages import Gaze, Pose
from hmdrt.replay import load_trace
from hmdrt.replay.convert import convert_trace
from hmdrt.spatial import gaze_direction

ROOT = Path(__file__).resolve().parent.parent
TRACES = ROOT / "tests" / "data" / "traces"
NATIVE = ROOT / "configs" / "traces" / "synthetic_250hz.jsonl.gz"  # gaze and head poses, 30 s at 250 Hz
TOLERANCE = 1e-12  # per direction component: the CSV reader normalises what it reads (a few 1e-16 in practice)
HMDRT_CSV = """t_ms,lx,ly,lz,rx,ry,rz,valid,depth_m
0,0.1,0.0,-1.0,-0.1,0.0,-1.0,1,0.75
4.5,0.1,0.2,-1.0,,,,1,
9,,,,-0.05,0.1,-1.0,1,2.5
13.5,0.0,0.0,-1.0,0.0,0.0,-1.0,0,
18,nan,0,-1,0,0,-1,1,
"""
SOURCES = {  # name: (file, reader options)
    "eyelink monocular": (TRACES / "raccoons.asc", {}),
    "eyelink binocular, lab geometry": (
        TRACES / "eyelink_binocular_example.asc",
        {"screen_width_mm": 376.0, "screen_height_mm": 301.0, "distance_mm": 700.0},
    ),
    "eyelink 2 kHz": (TRACES / "eyelink_mono2000_excerpt.asc", {}),
    "gazebase vr": (TRACES / "gazebase_vr_example.csv", {}),
    "pupil player": (TRACES / "pupil_player_v1_gaze_positions.csv", {}),
    "pupil player, monocular rows valid": (TRACES / "pupil_player_v1_gaze_positions.csv", {"min_confidence": 0.15}),
    "hmdrt csv": (None, {}),  # HMDRT_CSV, written to the test's folder
    "native": (NATIVE, {}),
}


def source_file(name: str, tmp_path: Path) -> tuple[Path, dict]:
    path, options = SOURCES[name]
    if path is None:
        path = tmp_path / "source.csv"
        path.write_text(HMDRT_CSV)
    return path, options


def gaze(samples: list) -> list[Gaze]:
    return [s for s in samples if isinstance(s, Gaze)]


def assert_same_gaze(got: list, expected: list) -> None:
    """Equal times, validity, eyes present, vergence depth and directions (to TOLERANCE) of every gaze sample."""
    got, expected = gaze(got), gaze(expected)
    assert len(got) == len(expected) > 0
    for a, b in zip(got, expected, strict=True):
        assert (a.t_host, a.valid) == (b.t_host, b.valid)
        assert (a.depth_m is None) == (b.depth_m is None), (a, b)
        if a.depth_m is not None:
            assert a.depth_m == pytest.approx(b.depth_m, rel=TOLERANCE)
        for eye in "CLR":
            u, v = getattr(a, eye), getattr(b, eye)
            assert (u is None) == (v is None), (a, b)
            if u is not None:
                assert max(abs(p - q) for p, q in zip(u, v, strict=True)) <= TOLERANCE


@pytest.mark.parametrize("name", SOURCES)
def test_every_format_converts_to_native_and_hmdrt_csv_and_back(tmp_path, name):
    source, options = source_file(name, tmp_path)
    original = load_trace(source, **options)
    assert any(s.valid for s in gaze(original.samples))

    native = convert_trace(source, tmp_path / "a.jsonl.gz", **options)
    assert native.samples == len(original.samples) and native.left_out == 0
    assert load_trace(tmp_path / "a.jsonl.gz").samples == original.samples  # native keeps every sample as it was

    table = convert_trace(source, tmp_path / "a.csv", **options)
    assert table.samples == len(gaze(original.samples))
    assert table.left_out == sum(isinstance(s, Pose) for s in original.samples)
    from_csv = load_trace(tmp_path / "a.csv")
    assert from_csv.malformed == 0
    assert_same_gaze(from_csv.samples, original.samples)
    assert all(s.t_dev == s.t_host for s in from_csv.samples)

    # and back: CSV -> native -> CSV, native -> CSV gives the same file as the source did
    convert_trace(tmp_path / "a.csv", tmp_path / "b.jsonl")
    assert_same_gaze(load_trace(tmp_path / "b.jsonl").samples, original.samples)
    convert_trace(tmp_path / "b.jsonl", tmp_path / "b.csv")
    assert_same_gaze(load_trace(tmp_path / "b.csv").samples, original.samples)
    convert_trace(tmp_path / "a.jsonl.gz", tmp_path / "c.csv.gz")
    assert gzip.decompress((tmp_path / "c.csv.gz").read_bytes()) == (tmp_path / "a.csv").read_bytes()


def test_an_eye_a_csv_row_leaves_empty_is_absent_not_invalid(tmp_path):
    """Rows of one eye (Pupil's monocular datums) stay valid through hmdrt CSV; a NaN or partly empty gaze does not."""
    path, _ = source_file("hmdrt csv", tmp_path)
    samples = load_trace(path).samples
    assert [s.valid for s in samples] == [True, True, True, False, False]
    assert samples[1].R is None and samples[2].L is None and samples[4].L is None
    assert [s.depth_m for s in samples] == [0.75, None, 2.5, None, None]
    pupil, options = SOURCES["pupil player, monocular rows valid"]
    monocular = [s for s in load_trace(pupil, **options).samples if s.valid and (s.L is None) != (s.R is None)]
    assert monocular, "the Pupil recording has valid rows of one eye"


def physio_rows(path: Path) -> list[list[str]]:
    return [line.split("\t") for line in gzip.decompress(path.read_bytes()).decode().splitlines()]


@pytest.mark.parametrize(
    "name, recordings",
    [
        ("eyelink binocular, lab geometry", {"eye1": ("left", "L"), "eye2": ("right", "R")}),
        ("gazebase vr", {"eye1": ("left", "L"), "eye2": ("right", "R"), "eye3": ("cyclopean", "C")}),
        ("native", {"eye1": ("left", "L"), "eye2": ("right", "R"), "eye3": ("cyclopean", "C")}),
    ],
)
def test_bids_export_columns_agree_with_the_sidecar_and_the_samples(tmp_path, name, recordings):
    source, options = source_file(name, tmp_path)
    samples = gaze(load_trace(source, **options).samples)
    done = convert_trace(source, tmp_path / "sub-01_task-replay_physio.tsv.gz", **options)
    assert sorted(p.name for p in done.written) == sorted(
        f"sub-01_task-replay_recording-{label}_physio.{ext}" for label in recordings for ext in ("tsv.gz", "json")
    )
    for label, (recorded_eye, eye) in recordings.items():
        stem = tmp_path / f"sub-01_task-replay_recording-{label}_physio"
        sidecar = json.loads(stem.with_suffix(".json").read_text())
        assert sidecar["RecordedEye"] == recorded_eye and sidecar["PhysioType"] == "eyetrack"
        assert sidecar["SampleCoordinateSystem"] == "eye-in-head" and sidecar["TaskName"] == "replay"
        assert sidecar["Columns"] == ["timestamp", "x_coordinate", "y_coordinate"]
        assert all(sidecar[c]["Units"] for c in sidecar["Columns"])
        rows = physio_rows(stem.with_name(stem.name + ".tsv.gz"))
        assert len(rows) == len(samples) and {len(r) for r in rows} == {len(sidecar["Columns"])}
        intervals = [b.t_host - a.t_host for a, b in zip(samples, samples[1:], strict=False)]
        median = sorted(intervals)[len(intervals) // 2]
        assert sidecar["SamplingFrequency"] == pytest.approx(1e9 / median, rel=1e-5)
        for row, s in zip(rows, samples, strict=True):
            assert Decimal(row[0]) * 1_000_000 == s.t_host  # ms, exact
            v = getattr(s, eye)
            if not s.valid or v is None:
                assert row[1:] == ["n/a", "n/a"]
            else:
                back = gaze_direction(float(row[1]), float(row[2]))
                assert max(abs(p - q) for p, q in zip(back, v, strict=True)) <= TOLERANCE


def test_bids_sidecar_has_the_keys_the_bids_schema_requires(tmp_path):
    """Checked against the BIDS schema (bidsschematools): REQUIRED physio and eye-tracking keys, their allowed
    values, and the eye-tracking columns first, in order."""
    schema = pytest.importorskip("bidsschematools.schema").load_schema()
    convert_trace(TRACES / "raccoons.asc", tmp_path / "sub-01_task-replay_physio.tsv.gz")
    sidecar = json.loads((tmp_path / "sub-01_task-replay_recording-eye1_physio.json").read_text())
    groups = schema.rules.sidecars.continuous
    required = {k for g in (groups.Continuous, groups.EyeTrack) for k, level in g.fields.items() if level == "required"}
    assert {"SamplingFrequency", "StartTime", "Columns", "RecordedEye", "SampleCoordinateSystem"} <= required
    assert required | {"PhysioType"} <= sidecar.keys()
    metadata = schema.objects.metadata
    for key in ("RecordedEye", "SampleCoordinateSystem"):
        assert sidecar[key] in metadata[key].enum
    assert sidecar["PhysioType"] == schema.objects.enums.PhysioTypeEyetrack.value
    columns = schema.rules.tabular_data.physio.PhysioEyeTracking.initial_columns
    assert sidecar["Columns"][: len(columns)] == [schema.objects.columns[c].name for c in columns]


@pytest.mark.skipif(importlib.util.find_spec("bids_validator_deno") is None, reason="bids-validator-deno not installed")
def test_bids_validator_finds_no_error_in_a_dataset_of_the_export(tmp_path):
    dataset = tmp_path / "dataset"
    (dataset / "sub-01" / "beh").mkdir(parents=True)
    (dataset / "dataset_description.json").write_text(json.dumps({"Name": "hmdrt export", "BIDSVersion": "1.11.0"}))
    source, options = source_file("eyelink binocular, lab geometry", tmp_path)
    convert_trace(source, dataset / "sub-01" / "beh" / "sub-01_task-replay_physio.tsv.gz", **options)
    run = subprocess.run(
        [sys.executable, "-c", "from bids_validator_deno import cli; cli()", "--format", "json", str(dataset)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    report = json.loads(run.stdout)
    errors = [issue for issue in report["issues"]["issues"] if issue["severity"] == "error"]
    assert not errors and run.returncode == 0, errors
    assert report["summary"]["totalFiles"] == 5


@pytest.mark.parametrize(
    "args, message",
    [
        (["raccoons.asc", "out.txt"], "out.txt: an output's name says its format; hmdrt writes BIDS eye-tracking"),
        (["gazebase_vr_example.csv", "o.csv", "--distance-mm", "700"], "takes no option 'distance_mm'"),
        (["raccoons.asc", "o.jsonl", "--min-confidence", "0.5"], "takes no option 'min_confidence'"),
        (["raccoons.asc", "exists.csv"], "exists.csv exists; --force replaces it"),
        (["raccoons.asc", "sub-01_recording-eye1_physio.tsv.gz"], "leave out the recording-<label> entity"),
    ],
)
def test_refused_conversions_are_one_line_and_write_nothing(tmp_path, capsys, monkeypatch, args, message):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "raccoons.asc").write_bytes((TRACES / "raccoons.asc").read_bytes())
    (tmp_path / "gazebase_vr_example.csv").write_bytes((TRACES / "gazebase_vr_example.csv").read_bytes())
    (tmp_path / "exists.csv").write_text("keep me\n")
    before = sorted(tmp_path.iterdir())
    assert cli.main(["convert", *args]) == 1
    err = capsys.readouterr().err
    assert err.startswith("hmdrt: error: ") and message in err and err.count("\n") == 1
    assert sorted(tmp_path.iterdir()) == before and (tmp_path / "exists.csv").read_text() == "keep me\n"


def test_cli_converts_says_what_it_wrote_and_replaces_with_force(tmp_path, capsys):
    out = tmp_path / "t.csv"
    assert cli.main(["convert", str(NATIVE), str(out)]) == 0
    said = capsys.readouterr().out
    assert said.startswith(f"{out}: 7500 samples as hmdrt CSV") and "7500 head-pose samples left out" in said
    out.write_text("old\n")
    assert cli.main(["convert", str(TRACES / "raccoons.asc"), str(out), "--force", "--distance-mm", "700"]) == 0
    assert out.read_text().startswith("t_ns,lx,ly,lz,valid\n")
