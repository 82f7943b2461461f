"""Fuzzing bytes and text from outside, trace files (replay.trace JSONL; EyeLink ASC, CSV, Pupil
Player, GazeBaseVR): bad input never gets in, never crashes."""

from __future__ import annotations

import gzip
import io
import json

import msgspec
import pytest
from hypothesis import strategies as st

from hmdrt.bus.messages import Gaze, Pose
from hmdrt.errors import ConfigError
from hmdrt.replay import load_trace, trace
from hmdrt.replay.trace import TraceWriter
from tests.fuzz.common import (
    fuzz,
    publishable,
    scratch,
    sparse,
)


def native_line(sample: Gaze | Pose) -> bytes:
    return msgspec.json.encode(sample)


NATIVE_SAMPLES = [
    Gaze(seq=0, t_host=0, C=(0.0, 0.0, -1.0), depth_m=1.5),
    Gaze(seq=1, t_host=4_000_000, valid=False),
    Pose(seq=0, t_host=0, position=(0.0, 1.6, 0.0), orientation=(1.0, 0.0, 0.0, 0.0)),
]
NATIVE_LINES = [native_line(s) for s in NATIVE_SAMPLES]
NATIVE_BAD_LINES = st.one_of(
    st.sampled_from(NATIVE_LINES).flatmap(lambda line: st.integers(1, len(line) - 1).map(lambda i: line[:i])),
    st.sampled_from(NATIVE_LINES).map(lambda line: line.replace(b'"seq":', b'"seq":"x","_":')),  # wrong type
    st.sampled_from([b"NaN", b"Infinity", b"-1e999", b"1e400", b'"\xff"', b"[1,2]"]).map(
        lambda v: b'{"kind":"gaze","seq":0,"t_host":0,"C":[' + v + b",0.0,-1.0]}"
    ),
    st.integers(10, 20_000).map(lambda d: b'{"kind":"gaze","x":' + b"[" * d + b"]" * d + b"}"),  # deep nesting
    st.integers(trace.MAX_LINE_BYTES + 1, trace.MAX_LINE_BYTES + 5000).map(lambda n: b"x" * n),  # over-long
    st.binary(min_size=1, max_size=80).filter(lambda b: b.strip() and b"\n" not in b and not b.rstrip().endswith(b"}")),
    st.just(b'{"kind":"blink","seq":0,"t_host":0}'),  # unknown kind
    st.sampled_from(NATIVE_LINES[:2]).map(lambda line: line.replace(b'"gaze"', b'"ga\xffze"')),  # not UTF-8
)


@fuzz(
    60,
    rows=st.lists(st.one_of(st.sampled_from(range(len(NATIVE_LINES))), NATIVE_BAD_LINES), max_size=12),
    gz=st.booleans(),
)
def test_native_trace_keeps_every_valid_line_and_counts_every_bad_one(rows, gz):
    """A JSONL trace (plain or gzip) mixing valid samples with truncated lines, wrong types, NaN/inf, non-UTF-8,
    deep nesting, unknown kinds, garbage and over-long lines reads the valid samples in order and counts
    malformed == the number of bad lines."""
    header = b'{"format":"hmdrt-trace","v":1,"device":"fuzz"}'
    lines = [NATIVE_LINES[r] if isinstance(r, int) else r for r in rows]
    body = b"\n".join([header, *lines]) + b"\n"
    path = scratch("fuzz.jsonl.gz" if gz else "fuzz.jsonl", gzip.compress(body, mtime=0) if gz else body)
    reading = load_trace(path)
    assert reading.samples == [NATIVE_SAMPLES[r] for r in rows if isinstance(r, int)]
    assert reading.malformed == sum(not isinstance(r, int) for r in rows)


@fuzz(
    150,
    name=st.sampled_from(["t.jsonl", "t.jsonl.gz", "t.asc", "t.csv", "t.csv.gz", "t.asc.gz"]),
    data=st.binary(max_size=400),
)
def test_any_bytes_as_any_trace_format_read_or_raise_config_error_naming_the_file(name, data):
    """Arbitrary bytes under every trace suffix read as samples that survive the bus decoder, or raise a
    ConfigError that names the file."""
    path = scratch(name, data)
    try:
        reading = load_trace(path)
    except ConfigError as exc:
        assert path.name in str(exc)
        return
    for sample in reading.samples:
        publishable(sample, "replay")


@pytest.mark.parametrize("name", ["empty.jsonl", "empty.jsonl.gz", "empty.asc", "empty.csv"])
def test_empty_trace_files_are_config_errors_naming_the_file(name):
    """An empty file of any trace format is a ConfigError with the file's name."""
    path = scratch(name, gzip.compress(b"") if name.endswith(".gz") else b"")
    with pytest.raises(ConfigError, match=name.replace(".", r"\.")):
        load_trace(path)


def test_trace_size_caps_refuse_by_size_before_reading(monkeypatch):
    """A trace over MAX_FILE_BYTES is refused by its size (a sparse file: nothing is read); a gzip file that
    inflates past MAX_FILE_BYTES (a decompression bomb) is refused once that much has been read. Regression:
    the inflated size had no cap."""
    big = sparse("big.jsonl", trace.MAX_FILE_BYTES + 1)
    with pytest.raises(ConfigError, match="big.jsonl"):
        load_trace(big)
    monkeypatch.setattr(trace, "MAX_FILE_BYTES", 100_000)
    header = b'{"format":"hmdrt-trace","v":1}\n'
    bomb = scratch("bomb.jsonl.gz", gzip.compress(header + NATIVE_LINES[0] * 0 + (NATIVE_LINES[0] + b"\n") * 5_000))
    assert bomb.stat().st_size < 100_000
    with pytest.raises(ConfigError, match="more than 100000 bytes"):
        load_trace(bomb)
    long_lines = scratch("long.csv.gz", gzip.compress(b"t_ms,yaw_deg,pitch_deg\n" + (b"1" * 70_000 + b"\n") * 3))
    with pytest.raises(ConfigError, match="more than 100000 bytes"):
        load_trace(long_lines)


ASC_HEADER = (
    "MSG 0 DISPLAY_COORDS 0 0 1919 1079\nSTART 1 LEFT RIGHT SAMPLES EVENTS\nSAMPLES GAZE LEFT RIGHT RATE 1000\n"
)
ASC_GOOD = st.builds(
    lambda t, xl, yl, xr, yr: f"{t} {xl:.1f} {yl:.1f} 1000.0 {xr:.1f} {yr:.1f} 1000.0 .....",
    st.integers(0, 10**9),
    *[st.floats(0, 1919)] * 4,
)
ASC_BAD = st.one_of(
    st.integers(0, 10**9).map(str),  # a time alone: too few columns
    st.builds(
        lambda t, w: f"{t} {w} 1.0 1000.0 1.0 1.0 1000.0", st.integers(0, 10**9), st.sampled_from(["abc", "1,5", "--"])
    ),
    st.sampled_from(["1e999999 1 1 1 1 1 1", "12x 1 1 1 1 1 1", "9" * 40 + " 1 1 1 1 1 1"]),
    st.just("12 \udcff\udcfe 1.0 1000.0 1.0 1.0 1000.0"),  # bytes ff fe: not UTF-8
    st.sampled_from(
        [
            "SBLINK X 5",
            "EBLINK L 5",
            "EBLINK R 5 abc 3",
            "MSG 1 DISPLAY_COORDS 0 0 nan 1",
            "MSG 1 DISPLAY_COORDS 5 5 1 1",
        ]
    ),
    st.integers(trace.MAX_LINE_BYTES + 1, trace.MAX_LINE_BYTES + 100).map(lambda n: "1" * n),
)
ASC_IGNORED = st.text(alphabet="EFIXSACDGMNOPQ ._-01234", max_size=30).filter(
    lambda t: (
        not t.lstrip()[:1].isdigit() and t.split()[:1] not in (["START"], ["SAMPLES"], ["SBLINK"], ["EBLINK"], ["MSG"])
    )
)


@fuzz(
    60,
    rows=st.lists(
        st.one_of(
            ASC_GOOD.map(lambda s: ("good", s)), ASC_BAD.map(lambda s: ("bad", s)), ASC_IGNORED.map(lambda s: ("", s))
        ),
        max_size=12,
    ),
)
def test_eyelink_keeps_every_sample_and_counts_exactly_the_bad_lines(rows):
    """An ASC recording with valid samples, bad sample and event lines (too few columns, non-numbers, huge or
    malformed times, bad blink and coordinate messages, over-long lines) and lines it ignores keeps every valid
    sample and counts malformed == the number of bad lines. Regression: a time of 1e999999 raised decimal.Overflow."""
    text = ASC_HEADER + "\n".join(s for _, s in rows) + "\n1 960 540 1000 960 540 1000 .....\n"
    reading = load_trace(scratch("fuzz.asc", text.encode("utf-8", "surrogateescape")))
    assert len(reading.samples) == 1 + sum(kind == "good" for kind, _ in rows)
    assert reading.malformed == sum(kind == "bad" for kind, _ in rows)
    for sample in reading.samples:
        publishable(sample, "eyelink")


CSV_FORMATS = {  # file name, header, a valid row
    "generic": ("g.csv", "t_ms,yaw_deg,pitch_deg,valid,depth_m", "{t},1.5,-2.0,1,0.8"),
    "gazebase": ("gb.csv", "n,x,y,lx,ly,rx,ry,xT,yT,zT", "{t},1.0,2.0,1.5,2.0,0.5,2.0,0,0,1"),
    "pupil": (
        "gaze_positions.csv",
        "gaze_timestamp,confidence,gaze_normal0_x,gaze_normal0_y,gaze_normal0_z,gaze_point_3d_x,gaze_point_3d_y,gaze_point_3d_z",
        "{t},0.9,0.1,0.0,0.99,0.0,0.0,500.0",
    ),
}
CSV_CELLS = st.one_of(
    st.sampled_from(["", ".", "nan", "NaN", "inf", "-inf", "1e308", "1e999", "abc", "1,5", '"1"', "\xff"]),
    st.floats().map(repr),
    st.text(st.characters(blacklist_categories=["Cs"], blacklist_characters="\r\n"), max_size=6),
)


@fuzz(
    60,
    fmt=st.sampled_from(sorted(CSV_FORMATS)),
    rows=st.lists(
        st.one_of(
            st.integers(0, 10**6).map(lambda t: ("good", t)),
            st.tuples(st.just("wide"), st.integers(1, 4)),
            st.tuples(st.just("narrow"), st.integers(1, 4)),
            st.tuples(st.just("text"), st.integers(0, 10**6)),
            st.tuples(st.just("latin1"), st.integers(0, 10**6)),
            st.tuples(st.just("cells"), st.lists(CSV_CELLS, min_size=1, max_size=12)),
        ),
        max_size=12,
    ),
)
def test_csv_traces_keep_valid_rows_and_count_rows_of_the_wrong_width(fmt, rows):
    """A CSV trace of each dialect with rows of too many or too few cells, non-numeric times and arbitrary cells
    (NaN, inf, non-UTF-8) keeps every valid row and counts each row of the wrong width or with a non-numeric time
    as malformed; whatever it reads survives the bus decoder (NaN gaze is invalid, never NaN on the bus)."""
    name, header, good = CSV_FORMATS[fmt]
    width = header.count(",") + 1
    lines, expected_good, expected_bad = [header.encode()], 0, 0
    for kind, arg in rows:
        if kind == "good":
            lines.append(good.format(t=arg).encode())
            expected_good += 1
        elif kind in ("wide", "narrow"):
            cells = good.format(t=1).split(",")
            lines.append(",".join(cells + ["1"] * arg if kind == "wide" else cells[: max(width - arg, 1)]).encode())
            expected_bad += 1
        elif kind in ("text", "latin1"):  # a time that is no number: letters, or bytes that are not UTF-8
            lines.append(good.format(t=arg).encode().replace(b",", b"t," if kind == "text" else b"\xff\xfe,", 1))
            expected_bad += 1
        else:
            lines.append(",".join(json.dumps(c) if "," in c or '"' in c else c for c in arg).encode())
    lines.append(good.format(t=10**7).encode())
    reading = load_trace(scratch(name, b"\n".join(lines)))
    assert len(reading.samples) >= expected_good + 1
    assert reading.malformed >= expected_bad
    assert len(reading.samples) + reading.malformed <= len(rows) + 1
    if all(kind != "cells" for kind, _ in rows):
        assert (len(reading.samples), reading.malformed) == (expected_good + 1, expected_bad)
    for sample in reading.samples:
        publishable(sample, "csv")


def test_native_trace_writer_lines_are_the_lines_this_module_treats_as_valid():
    """A TraceWriter's sample lines are exactly NATIVE_LINES (so the trace tests' valid lines are real ones)."""
    stream = io.BytesIO()
    writer = TraceWriter(stream)
    writer.header("fuzz")
    for sample in NATIVE_SAMPLES:
        writer.sample(sample)
    assert stream.getvalue().splitlines()[1:] == NATIVE_LINES
