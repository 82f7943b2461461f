"""Fuzzing bytes from outside, the frames log reader (hmdrt.telemetry.frames_log) behind `hmdrt export perfetto` and
`hmdrt report plot`: a bad line is an error naming the file and line, or a line that is not JSON skipped and counted,
never a crash, and whatever reads exports."""

from __future__ import annotations

import json

import msgspec
from hypothesis import strategies as st

from hmdrt.errors import HmdrtError
from hmdrt.telemetry.frames_log import MAX_LINE_BYTES, FramesHeader, read_frames_log
from hmdrt.telemetry.perfetto import trace_events
from hmdrt.telemetry.report import FrameRecord, SampleUse
from tests.fuzz.common import error_names_file, fuzz, mutations, scratch

HEADER = msgspec.json.encode(FramesHeader(vsync_hz=30.0, period_ns=33_333_333, virtual_time=True))


def line(vsync: int) -> bytes:
    """A frame record as the compositor logs it."""
    t = vsync * 33_333_333
    record = FrameRecord(
        vsync, vsync, "new", t, t - 30_000_000, t, t + 16_000_000, t - 30_000_000, t - 29_000_000, t - 3_000_000,
        False, SampleUse("eye", vsync, t - 40_000_000), SampleUse("head", vsync, t - 40_000_000), "rrm",
        {"fovea_deg": 10.0}, {"trace": 9.0, "trace/primary": 4.0}, 100, 20.0, 18.0, 0.5, level=1.0,
    )  # fmt: skip
    return msgspec.json.encode(record.to_dict())


VALID = b"\n".join([HEADER, line(0), line(1), line(2)]) + b"\n"
BAD_LINES = st.one_of(
    st.sampled_from(
        [
            b"",
            b"[]",
            b"null",
            b"NaN",
            b'{"vsync":"0"}',
            b"\xff\xfe",
            line(0).replace(b'"shown":"new"', b'"shown":"old"'),
            line(0).replace(b'"frame_ms":20.0', b'"frame_ms":-20.0'),
            line(0).replace(b'"frame_ms":20.0', b'"frame_ms":1e999'),
            line(0).replace(b'"stages_ms":{', b'"stages_ms":{"x":-1,'),
            line(0).replace(b'"level":1.0', b'"level":2.0'),
            line(0).replace(b'"rays":100', b'"rays":' + b"1" * 40),
            line(0).replace(b'"gaze":{', b'"gaze":{"seq":"x",'),
        ]
    ),
    st.integers(10, 20_000).map(lambda d: b'{"params":' + b"[" * d + b"]" * d + b"}"),  # deep nesting
    st.integers(MAX_LINE_BYTES + 1, MAX_LINE_BYTES + 5000).map(lambda n: b"x" * n),  # over-long
    st.binary(max_size=60).filter(lambda b: b"\n" not in b),
)


@fuzz(80, data=mutations(VALID))
def test_a_mutated_frames_log_reads_or_is_an_error_naming_the_file(data):
    """A valid log truncated, with a byte replaced, inserted or deleted: read (and exported to a timeline) or an
    HmdrtError naming the file."""
    path = scratch("fuzz.jsonl", data)
    try:
        reading = read_frames_log(path)
    except HmdrtError as exc:
        error_names_file(exc, path)
        return
    assert len(reading.records) <= 4
    trace_events(reading)


def is_json(text: bytes) -> bool:
    """Whether a line is JSON (UTF-8, no NaN or Infinity), by the standard library's parser."""

    def constant(name: str) -> None:
        raise ValueError(name)

    try:
        json.loads(text.decode("utf-8"), parse_constant=constant)
    except ValueError:  # also UnicodeDecodeError and json.JSONDecodeError
        return False
    except RecursionError:
        pass
    return True


@fuzz(80, lines=st.lists(st.one_of(st.none(), BAD_LINES), max_size=8))
def test_the_first_bad_line_is_named_by_its_number_and_lines_not_json_are_skipped(lines):
    """Good records (None) and bad lines after the header: an HmdrtError naming the file and the first bad line that
    is JSON (or too long), else the good records, with the lines that are not JSON at all (as a full disk tears
    them) counted."""
    body = [line(i) if text is None else text for i, text in enumerate(lines)]
    path = scratch("fuzz.jsonl", b"\n".join([HEADER, *body]) + b"\n")
    bad = [i for i, text in enumerate(lines) if text is not None and (len(text) > MAX_LINE_BYTES or is_json(text))]
    if not bad:
        reading = read_frames_log(path)
        assert [r.vsync for r in reading.records] == [i for i, text in enumerate(lines) if text is None]
        assert reading.corrupt == sum(text is not None for text in lines)
        return
    try:
        reading = read_frames_log(path)
    except HmdrtError as exc:
        assert str(exc).startswith(f"{path}:{bad[0] + 2}: "), str(exc)
    else:  # a "bad" line that decodes as a good record: only the random bytes could, and none do
        raise AssertionError(f"read {len(reading.records)} records past a bad line: {body[bad[0]]!r}")
