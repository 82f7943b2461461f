"""Importers of real trace formats: EyeLink ASC, GazeBase, GazeBaseVR, Pupil Player and hmdrt's CSV, via
load_trace."""

from __future__ import annotations

import csv
import logging
import math
from decimal import Decimal
from pathlib import Path

import numpy as np
import pytest
from hypothesis import strategies as st

from hmdrt import cli
from hmdrt.bus.messages import Gaze, usable
from hmdrt.errors import ConfigError
from hmdrt.replay import load_trace
from hmdrt.replay.formats.pupil_player import read_pupil_player
from hmdrt.replay.trace import write_trace
from tests.fuzz.common import fuzz, publishable, scratch

TRACES = Path(__file__).parent / "data" / "traces"
MONOCULAR = TRACES / "raccoons.asc"
BINOCULAR = TRACES / "eyelink_binocular_example.asc"
GAZEBASE = TRACES / "gazebase_vr_example.csv"
GAZEBASE_DESKTOP = TRACES / "gazebase_example.csv"  # real bytes: tests/data/traces/README.md
EYELINK_2KHZ = TRACES / "eyelink_mono2000_excerpt.asc"  # real bytes: tests/data/traces/README.md
PUPIL_V1 = TRACES / "pupil_player_v1_gaze_positions.csv"


def asc_file(path: Path) -> tuple[list[list[str]], tuple[str, ...], list[tuple[str, int, int]]]:
    """The file's own sample lines (split), recorded eyes (from START) and blinks (eye, first ms, last ms)."""
    samples, eyes, blinks = [], (), []
    for line in path.read_text(errors="replace").splitlines():
        fields = line.split()
        if line[:1].isdigit():
            samples.append(fields)
        elif fields[:1] == ["START"]:
            eyes = tuple(f[0] for f in fields if f in ("LEFT", "RIGHT"))
        elif fields[:1] == ["EBLINK"]:
            blinks.append((fields[1], int(fields[2]), int(fields[3])))
    return samples, eyes, blinks


def angle_deg(a, b) -> float:
    return math.degrees(math.acos(np.clip(np.dot(a, b), -1.0, 1.0)))


@pytest.mark.parametrize("path", [MONOCULAR, BINOCULAR])
def test_eyelink_recordings_import_every_sample_with_blinks_invalid(path):
    lines, eyes, blinks = asc_file(path)
    reading = load_trace(path)
    assert reading.malformed == 0 and len(reading.samples) == len(lines) > 300
    assert blinks, "the recording has blinks"
    for sample, fields in zip(reading.samples, lines, strict=True):
        t_ms = int(fields[0])
        assert sample.t_host == sample.t_dev == t_ms * 1_000_000
        assert sample.C is None and all(getattr(sample, e) is None for e in "LR" if e not in eyes)
        complete = True
        for k, eye in enumerate(eyes):
            blinking = any(e == eye and first <= t_ms <= last for e, first, last in blinks)
            missing = "." in fields[1 + 3 * k : 3 + 3 * k]
            gaze = getattr(sample, eye)
            assert (gaze is None) == (blinking or missing)
            complete &= gaze is not None
        assert sample.valid == complete and usable(sample) == complete
    inside = [s for s in reading.samples if any(a <= s.t_host // 1_000_000 <= b for _, a, b in blinks)]
    assert inside and not any(s.valid for s in inside)


def test_monocular_file_gives_the_recorded_eye_and_binocular_both():
    _, eyes, _ = asc_file(MONOCULAR)
    assert eyes == ("L",)
    assert any(s.L is not None for s in load_trace(MONOCULAR).samples)
    both = [s for s in load_trace(BINOCULAR).samples if s.valid]
    assert both and all(s.L is not None and s.R is not None for s in both)


def small_asc(tmp_path: Path, body: str) -> Path:
    path = tmp_path / "small.asc"
    path.write_text(body.replace("|", "\t"))
    return path


def test_display_coords_put_the_screen_centre_straight_ahead(tmp_path):
    w_px, h_px, w_mm, h_mm, d_mm = 1024, 768, 400.0, 300.0, 500.0
    path = small_asc(
        tmp_path,
        f"** header\nMSG|1 DISPLAY_COORDS 0 0 {w_px - 1} {h_px - 1}\nMSG|1 GAZE_COORDS 0.00 0.00 1919.00 1079.00\n"
        "START|10 |LEFT|SAMPLES|EVENTS\n"
        f"10|{w_px / 2}|{h_px / 2}|500.0|...\n"  # the centre
        f"11|{w_px}|{h_px / 2}|500.0|...\n"  # the right edge
        f"12|{w_px / 2}|0.0|500.0|...\n"  # the top edge
        "13|   .|   .|0.0|...\n",
    )
    samples = load_trace(path, screen_width_mm=w_mm, screen_height_mm=h_mm, distance_mm=d_mm).samples
    centre, right, top, missing = (np.array(s.L) if s.L else None for s in samples)
    assert np.allclose(centre, [0, 0, -1], rtol=0, atol=1e-12)
    assert np.allclose(right, np.array([w_mm / 2, 0, -d_mm]) / math.hypot(w_mm / 2, d_mm), rtol=0, atol=1e-12)
    assert np.allclose(top, np.array([0, h_mm / 2, -d_mm]) / math.hypot(h_mm / 2, d_mm), rtol=0, atol=1e-12)
    assert missing is None and not samples[3].valid and all(s.valid for s in samples[:3])


def test_real_recording_uses_its_display_coords_for_angles():
    """raccoons.asc: the centre of its DISPLAY_COORDS is EyeLink's central validation target, and every
    sample's angle from straight ahead is atan(distance from that centre on the screen / viewing distance)."""
    text = MONOCULAR.read_text(errors="replace")
    left, top, right, bottom = (float(v) for v in text.split("DISPLAY_COORDS")[1].split()[:4])
    cx, cy = (left + right + 1) / 2, (top + bottom + 1) / 2
    assert f"at {cx:.0f},{cy:.0f}" in text
    mm_per_px, d_mm = 0.25, 600.0
    width_mm, height_mm = (right - left + 1) * mm_per_px, (bottom - top + 1) * mm_per_px
    reading = load_trace(MONOCULAR, screen_width_mm=width_mm, screen_height_mm=height_mm, distance_mm=d_mm)
    lines, _, _ = asc_file(MONOCULAR)
    checked = 0
    for sample, fields in zip(reading.samples, lines, strict=True):
        if sample.valid:
            r_mm = math.hypot(float(fields[1]) - cx, float(fields[2]) - cy) * mm_per_px
            assert math.isclose(angle_deg(sample.L, [0, 0, -1]), math.degrees(math.atan(r_mm / d_mm)), abs_tol=1e-6)
            assert (sample.L[0] > 0) == (float(fields[1]) > cx) and (sample.L[1] > 0) == (float(fields[2]) < cy)
            checked += 1
    assert checked > 300


def test_eyelink_blink_events_drop_gaze_even_when_columns_are_filled(tmp_path):
    path = small_asc(
        tmp_path,
        "START|10 |LEFT|RIGHT|SAMPLES|EVENTS\n"
        "10|100.0|100.0|1.0|200.0|200.0|1.0|.....\n"
        "SBLINK L 11\n"
        "11|100.0|100.0|1.0|200.0|200.0|1.0|.....\n"  # numbers inside the left eye's blink
        "EBLINK L 11|12|2\n"
        "12|100.0|100.0|1.0|200.0|200.0|1.0|.....\n"  # after the event line, still within the blink
        "13|100.0|100.0|1.0|200.0|200.0|1.0|.....\n",
    )
    samples = load_trace(path).samples
    assert [s.valid for s in samples] == [True, False, False, True]
    assert [s.L is None for s in samples] == [False, True, True, False]
    assert all(s.R is not None for s in samples)


def test_eyelink_malformed_lines_are_counted(tmp_path):
    path = small_asc(
        tmp_path,
        "5|100.0|100.0|1.0\n"  # before START: layout unknown
        "START|10 |LEFT|RIGHT|SAMPLES|EVENTS\n"
        "SAMPLES|GAZE|LEFT|RIGHT|RATE|nan\n"
        "10|100.0|100.0|1.0|200.0|200.0|1.0|.....\n"
        "11|abc|100.0|1.0|200.0|200.0|1.0|.....\n"
        "12|100.0|100.0\n"
        "SBLINK Q 12\n"
        "MSG|13 DISPLAY_COORDS 0 0 -5 -5\n"
        f"{'9' * 70_000}\n"
        "14|100.0|100.0|1.0|200.0|200.0|1.0|.....\n",
    )
    reading = load_trace(path)
    assert [s.t_host // 1_000_000 for s in reading.samples] == [10, 14]
    assert reading.malformed == 7


def test_eyelink_2khz_pairs_of_whole_milliseconds_are_spaced_by_the_recorded_rate(caplog):
    """cili's 2000 Hz EyeLink CL recording (real bytes) gives each millisecond twice: the second sample of a
    pair lies 0.5 ms (1 / RATE 2000.00) after the first, the gaze is the file's own, and a log line says so."""
    lines, eyes, _ = asc_file(EYELINK_2KHZ)
    assert "RATE\t2000.00" in EYELINK_2KHZ.read_text() and eyes == ("R",)
    with caplog.at_level(logging.INFO, logger="hmdrt.replay.formats.eyelink"):
        reading = load_trace(EYELINK_2KHZ, screen_width_mm=400.0, screen_height_mm=300.0)
    assert reading.malformed == 0 and len(reading.samples) == len(lines) == 50
    first_of_ms = [k == 0 or fields[0] != lines[k - 1][0] for k, fields in enumerate(lines)]
    assert first_of_ms == [True, False] * 25  # the recording's own times repeat in pairs
    for sample, fields, first in zip(reading.samples, lines, first_of_ms, strict=True):
        assert sample.t_host == sample.t_dev == int(fields[0]) * 1_000_000 + (0 if first else 500_000)
        x_mm, y_mm = (float(fields[1]) - 512) * 400 / 1024, (384 - float(fields[2])) * 300 / 768  # DISPLAY_COORDS
        assert np.allclose(sample.R, np.array([x_mm, y_mm, -600.0]) / math.hypot(x_mm, y_mm, 600.0), atol=1e-12)
    assert set(np.diff([s.t_host for s in reading.samples])) == {500_000}  # strictly 2 kHz throughout
    assert [r.getMessage() for r in caplog.records] == [
        f"{EYELINK_2KHZ.name}: 25 samples repeat the millisecond of the sample before; each placed 0.5 ms after it"
        " (1 / RATE)"
    ]


@pytest.mark.parametrize(
    "change",
    ["drop the second of each pair", "RATE 1000", "times with -ftime fractions"],
)
def test_eyelink_times_that_do_not_repeat_or_come_below_1khz_are_kept(tmp_path, caplog, change):
    """No spacing is invented: distinct times (every other sample of the real 2 kHz file, or edf2asc -ftime's
    fractional times) and repeats in a block recorded at 1000 Hz keep the file's times, and nothing is logged."""
    text = EYELINK_2KHZ.read_text()
    kept, seen = [], set()
    for line in text.splitlines():
        stamp = line.split("\t")[0]
        if change == "drop the second of each pair" and stamp.isdigit() and stamp in seen:
            continue
        if change == "times with -ftime fractions" and stamp.isdigit():
            line = line.replace(stamp, f"{stamp}.{5 if stamp in seen else 0}", 1)
        seen.add(stamp)
        kept.append(line.replace("RATE\t2000.00", "RATE\t1000.00") if change == "RATE 1000" else line)
    path = tmp_path / "kept.asc"
    path.write_text("\n".join(kept) + "\n")
    with caplog.at_level(logging.INFO, logger="hmdrt.replay.formats.eyelink"):
        reading = load_trace(path)
    lines, _, _ = asc_file(path)
    assert reading.malformed == 0 and len(reading.samples) == len(lines) == (25 if change.startswith("drop") else 50)
    assert [s.t_host for s in reading.samples] == [round(Decimal(f[0]) * 1_000_000) for f in lines]
    assert not caplog.records


def test_gazebase_vr_rows_convert_with_yaw_right_and_pitch_up():
    rows = list(csv.DictReader(GAZEBASE.open()))
    reading = load_trace(GAZEBASE)
    assert reading.malformed == 0 and len(reading.samples) == len(rows)
    for sample, row in zip(reading.samples, rows, strict=True):
        assert sample.t_host == round(float(row["n"]) * 1e6) and sample.valid
        for eye, (yaw, pitch) in {"C": ("x", "y"), "L": ("lx", "ly"), "R": ("rx", "ry")}.items():
            yaw, pitch = math.radians(float(row[yaw])), math.radians(float(row[pitch]))
            v = np.array(getattr(sample, eye))
            assert np.sign(v[0]) == np.sign(yaw) and np.sign(v[1]) == np.sign(pitch) and v[2] < 0
            assert math.isclose(math.atan2(v[0], -v[2]), yaw, abs_tol=1e-12)
            assert math.isclose(math.asin(v[1]), pitch, abs_tol=1e-12)
    # converging on a central target, the left eye turns right of the right eye
    assert all(s.L[0] > s.R[0] for s in reading.samples)


def test_gazebase_vr_nan_makes_a_sample_invalid(tmp_path):
    lines = GAZEBASE.read_text().splitlines()
    cells = lines[2].split(",")
    cells[3] = "NaN"  # lx
    path = tmp_path / "gazebase_nan.csv"
    path.write_text("\n".join([*lines[:2], ",".join(cells), *lines[3:], "1,2,3"]) + "\n")
    reading = load_trace(path)
    assert reading.malformed == 1 and len(reading.samples) == len(lines) - 1
    bad = reading.samples[1]
    assert not bad.valid and bad.L is None and bad.R is not None and bad.C is not None
    assert all(s.valid for k, s in enumerate(reading.samples) if k != 1)


def test_gazebase_rows_convert_to_the_left_eye_with_yaw_right_and_pitch_up():
    """GazeBase's real first rows (a reading recording, by their NaN targets and labels): every row a valid
    left-eye sample at n ms, with yaw = x and pitch = y (top left of the text: left and up)."""
    rows = list(csv.DictReader(GAZEBASE_DESKTOP.open()))
    reading = load_trace(GAZEBASE_DESKTOP)
    assert reading.device == "gazebase" and reading.malformed == 0 and len(reading.samples) == len(rows) == 10
    for sample, row in zip(reading.samples, rows, strict=True):
        assert sample.t_host == sample.t_dev == int(row["n"]) * 1_000_000 and sample.valid
        assert sample.C is None and sample.R is None
        v = np.array(sample.L)
        assert v[0] < 0 and v[1] > 0 and v[2] < 0  # x = -16 (left), y = +5.9 (up)
        assert math.isclose(math.degrees(math.atan2(v[0], -v[2])), float(row["x"]), abs_tol=1e-12)
        assert math.isclose(math.degrees(math.asin(v[1])), float(row["y"]), abs_tol=1e-12)


def test_gazebase_columns_by_name_invalid_samples_and_malformed_rows(tmp_path):
    """An excerpt made to GazeBase's published layout (not real bytes): the other column order GazeBase uses
    (n,x,y,val,xT,yT,dP,lab), an invalid sample as GazeBase writes it (val 4, x, y and dP NaN), one with val 0
    but a gaze beyond 90 deg, and rows that are malformed: a val, x or time that is no number, the wrong
    width, an over-long line. Valid and invalid samples are kept, the malformed rows counted, none fatal."""
    lines = [
        "n,x,y,val,xT,yT,dP,lab",
        "0,1.5,-2.25,0,0,0,3150,1",
        "1,NaN,NaN,4,0,0,NaN,3",
        "2,1.5,-2.25,2,0,0,3150,1",  # val not 0: invalid, whatever x and y say
        "3,95.0,0.0,0,0,0,3150,1",  # beyond 90 deg: no direction, invalid
        "4,1.5,-2.25,zero,0,0,3150,1",
        "5,abc,-2.25,0,0,0,3150,1",
        "6.5.1,1.5,-2.25,0,0,0,3150,1",
        "7,1.5,-2.25,0,0,0,3150",
        "8," + "1" * 70_000 + ",0,0,0,0,3150,1",
        "9,-3.0,4.0,0,0,0,3150,2",
    ]
    path = tmp_path / "S_1001_S1_RAN.csv"
    path.write_text("\n".join(lines) + "\n")
    reading = load_trace(path)
    assert reading.malformed == 5
    assert [(s.t_host // 1_000_000, s.valid) for s in reading.samples] == [
        (0, True),
        (1, False),
        (2, False),
        (3, False),
        (9, True),
    ]
    yaw, pitch = (
        math.degrees(a)
        for a in (math.atan2(reading.samples[-1].L[0], -reading.samples[-1].L[2]), math.asin(reading.samples[-1].L[1]))
    )
    assert math.isclose(yaw, -3.0, abs_tol=1e-9) and math.isclose(pitch, 4.0, abs_tol=1e-9)
    assert reading.samples[1].L is None and reading.samples[2].L is not None


@pytest.mark.parametrize(
    "content, message",
    [
        ("n,x,y,dP,lab\n0,1,2,3000,1\n", r"not a known gaze CSV: found columns \[n, x, y, dP, lab\];.*GazeBase needs"),
        ("n,x,y,val\n", "holds no valid gazebase gaze samples"),
        ("n,x,y,val\n0,1,2,x\n1,1,2,y\n", r"no valid gazebase gaze samples \(0 samples read, 2 malformed"),
    ],
)
def test_gazebase_files_without_a_valid_sample_are_one_clear_line(tmp_path, capsys, content, message):
    """A GazeBase-like CSV without val, or without a valid row, is a ConfigError naming the file, which the CLI
    prints as one line."""
    path = tmp_path / "gb.csv"
    path.write_text(content)
    with pytest.raises(ConfigError, match=message) as refused:
        load_trace(path)
    assert str(path) in str(refused.value) and "\n" not in str(refused.value)
    assert cli.main(["emulate", "smi", "--trace", str(path), "--port", "0", "--duration", "0.01"]) == 1
    assert capsys.readouterr().err == f"hmdrt: error: {refused.value}\n"


GAZEBASE_CELLS = st.one_of(
    st.sampled_from(["", ".", "nan", "NaN", "inf", "-inf", "1e308", "1e999", "abc", "1,5", '"1"', "\xff", "0", "4"]),
    st.floats().map(repr),
    st.text(st.characters(blacklist_categories=["Cs"], blacklist_characters="\r\n"), max_size=6),
)


@fuzz(
    60,
    order=st.permutations(["n", "x", "y", "val", "dP", "lab", "xT", "yT"]),
    rows=st.lists(
        st.one_of(
            st.tuples(st.just("good"), st.integers(0, 10**6)),
            st.tuples(st.just("invalid"), st.integers(0, 10**6)),
            st.tuples(st.just("width"), st.integers(1, 3)),
            st.tuples(st.just("time"), st.sampled_from(["t", "1.2.3", "9" * 40, "1e999", ""])),
            st.tuples(st.just("cells"), st.lists(GAZEBASE_CELLS, min_size=8, max_size=8)),
        ),
        max_size=12,
    ),
)
def test_gazebase_keeps_valid_and_invalid_samples_and_counts_malformed_rows(order, rows):
    """A GazeBase CSV with its columns in any order, valid rows, invalid ones (val 4, NaN gaze), rows of the
    wrong width or with a time that is no number, and arbitrary cells keeps every valid and invalid row as a
    sample, counts the malformed ones, and whatever it reads survives the bus decoder."""

    def line(values: dict[str, str]) -> str:
        return ",".join(values[name] for name in order)

    good = {"x": "1.5", "y": "-2.0", "val": "0", "dP": "3000", "lab": "1", "xT": "NaN", "yT": "NaN"}
    lines, kept, bad = [",".join(order)], 0, 0
    for kind, arg in rows:
        if kind in ("good", "invalid"):
            values = {**good, "n": str(arg)}
            if kind == "invalid":
                values.update(x="NaN", y="NaN", val="4", dP="NaN")
            lines.append(line(values))
            kept += 1
        elif kind == "width":
            lines.append(line({**good, "n": "1"}) + ",1" * arg)
            bad += 1
        elif kind == "time":
            lines.append(line({**good, "n": arg}))
            bad += 1
        else:
            lines.append(",".join(f'"{c}"' if "," in c or '"' in c else c for c in arg))
    lines.append(line({**good, "n": "10000000"}))
    reading = load_trace(scratch("gazebase.csv", "\n".join(lines).encode("utf-8", "surrogateescape")))
    assert reading.malformed >= bad and len(reading.samples) >= kept + 1
    if all(kind != "cells" for kind, _ in rows):
        assert (len(reading.samples), reading.malformed) == (kept + 1, bad)
    for sample in reading.samples:
        publishable(sample, "gazebase")


PUPIL_HEADER = (
    "gaze_timestamp,world_index,confidence,norm_pos_x,norm_pos_y,base_data,gaze_point_3d_x,gaze_point_3d_y,"
    "gaze_point_3d_z,eye_center0_3d_x,eye_center0_3d_y,eye_center0_3d_z,gaze_normal0_x,gaze_normal0_y,"
    "gaze_normal0_z,eye_center1_3d_x,eye_center1_3d_y,eye_center1_3d_z,gaze_normal1_x,gaze_normal1_y,gaze_normal1_z"
)


def pupil_row(t: float, confidence: float, point=("", "", ""), normal0=("", "", ""), normal1=("", "", "")) -> str:
    cells = [t, 0, confidence, 0.5, 0.5, f"{t}-0", *point, 20, 0, 0, *normal0, -40, 0, 0, *normal1]
    return ",".join(str(c) for c in cells)


def opencv_to_head(v) -> np.ndarray:
    v = np.array([v[0], -v[1], -v[2]], dtype=float)
    return v / np.linalg.norm(v)


def test_pupil_player_normals_become_head_frame_directions(tmp_path):
    s = math.sqrt(0.5)
    rows = [  # (timestamp s, confidence, gaze_point_3d mm, normal0 = right eye, normal1 = left eye), OpenCV y down
        (-12.5, 0.95, (100.0, -50.0, 800.0), (0.1, -0.05, 0.99), (s, 0.0, s)),
        (-12.49, 0.99, (0.0, 0.0, 500.0), (0.0, 0.6, 0.8), ("", "", "")),  # monocular: eye 0 only
        (-12.48, 0.5, (0.0, 0.0, 500.0), (0.0, 0.0, 1.0), (0.0, 0.0, 1.0)),  # below Pupil's 0.6 confidence
    ]
    path = tmp_path / "gaze_positions.csv"
    path.write_text("\n".join([PUPIL_HEADER, *(pupil_row(*r) for r in rows), "x,y,z", "-12.47,1,oops"]) + "\n")
    reading = load_trace(path)
    assert reading.malformed == 2 and len(reading.samples) == len(rows)
    for sample, (t, confidence, point, normal0, normal1) in zip(reading.samples, rows, strict=True):
        assert sample.t_host == sample.t_dev == round(t * 1e9)
        assert sample.valid == (confidence >= 0.6)
        assert np.allclose(sample.R, opencv_to_head(normal0), rtol=0, atol=1e-12)
        assert np.allclose(sample.C, opencv_to_head(point), rtol=0, atol=1e-12)
        assert math.isclose(sample.depth_m, np.linalg.norm(point) / 1000)
        assert (sample.L is None) if normal1[0] == "" else np.allclose(sample.L, opencv_to_head(normal1), atol=1e-12)
    first = reading.samples[0]
    assert first.C[1] > 0 and first.L[0] > 0.7 and first.L[2] < 0  # the point is up (y down in OpenCV), L right
    assert reading.samples[1].R[1] < 0  # +y in OpenCV looks down
    assert load_trace(path, min_confidence=0.4).samples[2].valid


@pytest.mark.parametrize(
    "names",
    [("timestamp", "index"), ("world_timestamp", "world_index"), ("gaze_timestamp", "world_index")],
)
def test_pupil_player_v1_export_reads_like_a_current_one(tmp_path, names):
    """A real export of the older Raw Data Exporter (header `timestamp,index,...`, from gaze2svg) reads row by
    row like a current one, and so does the same file under the late-2018 and the current time column names."""
    text = PUPIL_V1.read_bytes().decode()
    assert text.startswith("timestamp,index,confidence,") and "\r\n" in text
    path = tmp_path / "gaze_positions.csv"
    path.write_bytes(text.replace("timestamp,index,", ",".join(names) + ",", 1).encode())
    rows = list(csv.DictReader(PUPIL_V1.open(newline="")))
    reading = load_trace(path)
    assert reading.malformed == 0 and len(reading.samples) == len(rows) == 12
    for sample, row in zip(reading.samples, rows, strict=True):
        assert sample.t_host == sample.t_dev == round(Decimal(row["timestamp"]) * 10**9)
        assert sample.valid == (float(row["confidence"]) >= 0.6)
        for eye, prefix in (("R", "gaze_normal0_"), ("L", "gaze_normal1_"), ("C", "gaze_point_3d_")):
            cells = [float(row[prefix + axis] or "nan") for axis in "xyz"]
            got = getattr(sample, eye)
            assert (got is None) if math.isnan(cells[0]) else np.allclose(got, opencv_to_head(cells), atol=1e-12)
    assert {(s.L is None, s.R is None) for s in reading.samples} == {(True, False), (False, True), (False, False)}
    assert [s.valid for s in reading.samples] == [False] * 5 + [True, True, False] + [True] * 4


def test_pupil_reader_refuses_a_foreign_header_naming_its_columns(tmp_path):
    path = tmp_path / "pupil_positions.csv"
    path.write_text("pupil_timestamp,world_index,eye_id,confidence,diameter\n1.0,0,0,0.9,30\n")
    with pytest.raises(ConfigError, match=r"found columns \[pupil_timestamp, world_index, eye_id, confidence"):
        read_pupil_player(path)


@pytest.mark.parametrize(
    "header, row, expect",
    [
        ("t_ms,yaw_deg,pitch_deg", "4.5,10,-5", {"t": 4_500_000, "C": (10.0, -5.0)}),
        ("t_ns,cx,cy,cz,valid", "123456789012345678,0,0,-2,true", {"t": 123456789012345678, "C": (0.0, 0.0)}),
        ("t_s,lx,ly,lz,rx,ry,rz,depth_m,note", "1.25,0,0,-1,0.1,0,-1,2.5,hi", {"t": 1_250_000_000, "L": (0.0, 0.0)}),
    ],
)
def test_generic_csv_variants(tmp_path, header, row, expect):
    path = tmp_path / "ours.csv"
    path.write_text(f"{header}\n{row}\n\n{row.replace(',', ';')}\n")
    reading = load_trace(path)
    assert reading.malformed == 1 and len(reading.samples) == 1
    sample = reading.samples[0]
    assert sample.t_host == sample.t_dev == expect["t"] and sample.valid and usable(sample)
    eye = "C" if "C" in expect else "L"
    v = getattr(sample, eye)
    assert math.isclose(math.degrees(math.atan2(v[0], -v[2])), expect[eye][0], abs_tol=1e-9)
    assert math.isclose(math.degrees(math.asin(v[1])), expect[eye][1], abs_tol=1e-9)
    if "depth_m" in header:
        assert sample.depth_m == 2.5 and sample.R[0] > 0


def test_generic_csv_valid_column_missing_gaze_and_overlong_lines(tmp_path):
    path = tmp_path / "ours.csv"
    long_row = "5," + "0" * 70_000 + ",0,1"
    path.write_text(f"t_ms,yaw_deg,pitch_deg,valid\n0,0,0,1\n1,0,0,0\n2,,0,1\n3,nan,0,1\n4,0,0,maybe\n{long_row}\n")
    reading = load_trace(path)
    assert [s.valid for s in reading.samples] == [True, False, False, False]
    assert reading.samples[1].C is not None and reading.samples[2].C is None and reading.malformed == 2


@pytest.mark.parametrize(
    "header, message",
    [
        ("t_ms,t_s,yaw_deg,pitch_deg", "exactly one time column"),
        ("t_ms,yaw_deg,pitch_deg,cx,cy,cz", "combined gaze twice"),
        ("t_ms,lx,ly", "but not lz"),
        ("t_ms,pupil_size", "no gaze columns"),
        ("time,yaw,pitch", r"not a known gaze CSV: found columns \[time, yaw, pitch\]; Pupil Player needs"),
    ],
)
def test_csv_schema_errors_are_one_clear_sentence(tmp_path, header, message):
    path = tmp_path / "bad.csv"
    path.write_text(f"{header}\n0,0,0\n")
    with pytest.raises(ConfigError, match=message):
        load_trace(path)


@pytest.mark.parametrize("source", ["pupil v1", "gazebase", "gazebase desktop", "hmdrt csv", "native"])
def test_blank_lines_before_a_header_are_skipped(tmp_path, source):
    """Blank (and whitespace-only) lines before the header row of each CSV format, and before a native trace's
    header, are skipped: the file reads as it does without them."""
    if source == "native":
        plain = tmp_path / "t.jsonl"
        write_trace(plain, [Gaze(seq=k, t_host=k * 4_000_000, C=(0.0, 0.0, -1.0)) for k in range(3)], device="eye")
    elif source == "hmdrt csv":
        plain = tmp_path / "ours.csv"
        plain.write_text("t_ms,yaw_deg,pitch_deg\n0,1,2\n4,3,4\n")
    else:
        plain = {"pupil v1": PUPIL_V1, "gazebase": GAZEBASE, "gazebase desktop": GAZEBASE_DESKTOP}[source]
    padded = tmp_path / f"padded{''.join(plain.suffixes)}"
    padded.write_bytes(b"\n\r\n  \t\n" + plain.read_bytes())
    expected = load_trace(plain)
    assert load_trace(padded) == expected and expected.samples


def test_unknown_csv_names_found_and_expected_columns_and_the_cli_says_it_in_one_line(tmp_path, capsys):
    """A CSV no format reads (here a Pupil export without confidence, with a long header) is refused naming the
    columns found (the first 24, each cut at 40 characters) and what each CSV format needs; the CLI prints that
    one line, no traceback."""
    names = ["gaze_timestamp", "world_index", "x" * 100, *(f"c{k}" for k in range(30))]
    path = tmp_path / "gaze_positions.csv"
    path.write_text(",".join(names) + "\n" + ",".join("0" * len(names)) + "\n")
    with pytest.raises(ConfigError) as refused:
        load_trace(path)
    message = str(refused.value)
    assert message == (
        f"{path} is not a known gaze CSV: found columns [gaze_timestamp, world_index, {'x' * 40}..., "
        + ", ".join(f"c{k}" for k in range(21))
        + ", ... (33 in all)]; Pupil Player needs [gaze_timestamp, confidence] or [world_timestamp, world_index,"
        " confidence] or [timestamp, index, confidence]; GazeBaseVR needs [n, x, y, lx, ly, rx, ry]; GazeBase needs"
        " [n, x, y, val]; hmdrt CSV needs one of [t_ns, t_ms, t_s] and gaze columns"
    )
    assert cli.main(["emulate", "smi", "--trace", str(path), "--port", "0", "--duration", "0.01"]) == 1
    assert capsys.readouterr().err == f"hmdrt: error: {message}\n"


def test_native_traces_still_load_plain_and_gzipped(tmp_path):
    samples = [Gaze(seq=k, t_host=k * 4_000_000, C=(0.0, 0.0, -1.0)) for k in range(5)]
    for name in ("t.jsonl", "t.jsonl.gz"):
        write_trace(tmp_path / name, samples, device="eye")
        reading = load_trace(tmp_path / name)
        assert reading.samples == samples and reading.device == "eye"


@pytest.mark.parametrize(
    "name, content, options, message",
    [
        ("trace.txt", "t_ms,yaw_deg,pitch_deg\n0,0,0\n", {}, "EyeLink ASC"),
        ("missing.asc", None, {}, "not found"),
        ("blank.asc", "** nothing here\nMSG\t1 hello\n", {}, "no valid eyelink gaze samples"),
        ("empty.csv", "", {}, "not a known gaze CSV: found no columns"),
        ("g.csv", "n,x,y,lx,ly,rx,ry\n0,nan,nan,nan,nan,nan,nan\n", {}, "no valid gazebase_vr"),
        ("d.csv", "n,x,y,val,dP,lab,xT,yT\n0,NaN,NaN,4,NaN,0,NaN,NaN\n", {}, "no valid gazebase gaze samples"),
        ("o.csv", "t_ms,yaw_deg,pitch_deg\n0,0,0\n", {"distance_mm": 600}, "takes no option 'distance_mm'"),
        ("e.asc", "START\t1\tLEFT\n1\t0\t0\t1\n", {"distance_mm": -1}, "positive number of millimetres"),
    ],
)
def test_unsupported_or_empty_files_are_refused(tmp_path, name, content, options, message):
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    with pytest.raises(ConfigError, match=message):
        load_trace(path, **options)
