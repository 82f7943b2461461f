"""Fuzzing every decoder of bytes and text from outside (issue 7): bad input never gets in, never crashes.

Each decoder is fed arbitrary bytes, mutations of valid input and inputs built to break one rule at a
time (wrong types, missing keys, huge length headers, deep nesting, unknown versions, truncation,
non-UTF-8, NaN and inf, over-long lines, empty files). The guarantee checked everywhere: the decoder
returns a well-formed value, or raises its own documented error (MalformedMessage, SmiError,
FrameError, Dk2FormatError, RazorFormatError, HatireFormatError, MalformedDatum, ConfigError,
SceneError), or counts the input as dropped (a driver's `malformed`, a trace's `malformed`) exactly
once; no other exception type escapes, nothing hangs, and sizes are refused by a cap before anything
is allocated for them. Everything a driver or an importer lets through must survive the bus decoder.

The default run takes well under a minute; `-m slow` runs every property with EXTENDED times as many
examples.
"""

from __future__ import annotations

import gzip
import io
import json
import math
import socket
import struct
import tempfile
import threading
import time
import tracemalloc
import zlib
from pathlib import Path

import msgspec
import numpy as np
import pytest
import trimesh
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image as PILImage

from drivers import open_driver
from drivers.fove import FoveDriver
from drivers.hid import HidDriver
from drivers.protocols import dk2, fove, hatire, razor, smi
from drivers.protocols.hatire import HatireFrame
from drivers.pupil import MalformedDatum, PupilDriver, decode_gaze
from drivers.serial_port import PROTOCOLS as SERIAL_PROTOCOLS
from hmdrt.bus import messages
from hmdrt.bus.messages import ClockEstimate, Gaze, MalformedMessage, Pose, Status
from hmdrt.compositor.config import RunConfig, load_config
from hmdrt.configfile import MAX_TOML_BYTES, read_toml
from hmdrt.errors import ConfigError, SceneError
from hmdrt.evaluate.config import EvalConfig, load_eval_config
from hmdrt.optics.profiles import HmdProfile, get_profile
from hmdrt.scene.files import MAX_FILE_BYTES as MAX_MESH_BYTES
from hmdrt.scene.files import MESH_SUFFIXES, SceneFile, load_image, load_mesh_file, load_scene_file
from hmdrt.scene.model import Scene
from replay import load_trace, trace
from replay.trace import TraceWriter

from .helpers import SECTION7_GAZE, ScriptedFoveServer, VirtualClock, at_least, collect

pytestmark = [  # corrupt input makes PIL and trimesh warn about what they skip; expected here
    pytest.mark.filterwarnings("ignore::UserWarning:PIL"),
    pytest.mark.filterwarnings("ignore::RuntimeWarning:trimesh"),
]
EXTENDED = 20  # the slow run's examples per default-run example
RUNS = [pytest.param(1, id="default"), pytest.param(EXTENDED, id="extended", marks=pytest.mark.slow)]
MESHES = Path(__file__).parent / "data" / "meshes"
_SCRATCH = tempfile.TemporaryDirectory(prefix="hmdrt-fuzz-")


def fuzz(examples: int, **strategies):
    """A property run with `examples` examples by default and EXTENDED times as many under -m slow.

    The decorated function's name and docstring state the property; its arguments are drawn from
    `strategies`.
    """

    def decorate(check):
        @pytest.mark.parametrize("scale", RUNS)
        def test(scale):
            run = given(**strategies)(check)
            settings(
                max_examples=examples * scale,
                deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
            )(run)()

        test.__name__, test.__qualname__, test.__doc__ = check.__name__, check.__qualname__, check.__doc__
        return test

    return decorate


def scratch(name: str, data: bytes | str) -> Path:
    """A file of the given content in this module's scratch folder (overwritten by the next example)."""
    path = Path(_SCRATCH.name) / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def sparse(name: str, size: int) -> Path:
    """A file that claims `size` bytes without taking them on disk: a size check must refuse it unread."""
    path = Path(_SCRATCH.name) / name
    with path.open("wb") as f:
        f.truncate(size)
    return path


def publishable(sample: Gaze | Pose, device: str = "fuzz") -> None:
    """The sample survives the bus decoder unchanged: nothing a driver or importer lets through is refused
    (or crashes the encoder) on the way to the compositor."""
    _, _, back = messages.decode(messages.encode(sample, device))
    assert back == sample


def mutations(data: bytes) -> st.SearchStrategy[bytes]:
    """`data` truncated, with a byte replaced, with bytes inserted, or with a span deleted."""
    n = len(data)
    return st.one_of(
        st.integers(0, max(n - 1, 0)).map(lambda i: data[:i]),
        st.tuples(st.integers(0, max(n - 1, 0)), st.integers(0, 255)).map(
            lambda t: data[: t[0]] + bytes([t[1]]) + data[t[0] + 1 :]
        ),
        st.tuples(st.integers(0, n), st.binary(min_size=1, max_size=16)).map(
            lambda t: data[: t[0]] + t[1] + data[t[0] :]
        ),
        st.tuples(st.integers(0, n), st.integers(1, 16)).map(lambda t: data[: t[0]] + data[t[0] + t[1] :]),
    )


SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**64 - 1),
    st.floats(),
    st.text(max_size=12),
    st.binary(max_size=12),
)
MSGPACK_VALUES = st.recursive(
    SCALARS,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


# --- the bus: hmdrt.bus.messages.decode -----------------------------------------------------------------------

BUS_MESSAGES = [
    Gaze(seq=7, t_host=1_000, t_dev=900, C=(0.0, 0.0, -1.0), L=(0.1, 0.0, -0.995), R=(-0.1, 0.0, -0.995), depth_m=1.5),
    Gaze(seq=8, t_host=2_000, valid=False),
    Pose(seq=3, t_host=5_000, position=(0.0, 1.6, 0.0), orientation=(1.0, 0.0, 0.0, 0.0), t_dev=4_000),
    Status(device="smi", state="connected", t_host=9, samples=10, malformed=2, clock=ClockEstimate(1.0, 2.0, 3.0)),
]
BUS_FRAMES = [messages.encode(m, "dev") for m in BUS_MESSAGES]
BUS_FIELDS = [msgspec.msgpack.decode(frames[1]) for frames in BUS_FRAMES]
NOT_A_NUMBER_OR_VECTOR = st.one_of(st.text(max_size=8), st.binary(max_size=8), st.dictionaries(st.text(), SCALARS))
NUMERIC_KEYS = {
    "gaze": ("seq", "t_host", "t_dev", "C", "L", "R", "depth_m", "valid"),
    "pose": ("seq", "t_host", "t_dev", "position", "orientation", "valid"),
    "status": ("t_host", "samples", "invalid", "dropped", "malformed", "reconnects", "clock"),
}


def bus_outcome(frames: list[bytes]) -> Gaze | Pose | Status | None:
    """The decoded message, or None when decode refused it with MalformedMessage (anything else fails)."""
    try:
        kind, device, message = messages.decode(frames)
    except MalformedMessage:
        return None
    assert device and messages.decode(messages.encode(message, device)) == (kind, device, message)
    return message


@fuzz(300, frames=st.lists(st.binary(max_size=64), max_size=4))
def test_bus_decode_of_any_frames_is_a_message_or_malformed(frames):
    """Arbitrary frames decode to a message that round-trips, or raise MalformedMessage."""
    bus_outcome(frames)


@fuzz(300, frames=st.sampled_from(BUS_FRAMES).flatmap(lambda f: st.tuples(mutations(f[0]), mutations(f[1]))))
def test_bus_decode_of_corrupted_messages_is_a_message_or_malformed(frames):
    """Valid gaze, pose and status frames truncated, overwritten, extended or cut decode or raise MalformedMessage."""
    bus_outcome(list(frames))


@fuzz(
    300,
    which=st.integers(0, len(BUS_FIELDS) - 1),
    change=st.one_of(
        st.tuples(st.just("drop"), st.integers(0, 20)),
        st.tuples(st.just("extra"), st.text(min_size=1, max_size=8).filter(lambda k: k != "v"), MSGPACK_VALUES),
        st.tuples(st.just("retype"), st.integers(0, 20), NOT_A_NUMBER_OR_VECTOR),
    ),
)
def test_bus_missing_unknown_or_mistyped_fields_are_malformed(which, change):
    """A message missing a required field, with an unknown field, or with a field of the wrong type is malformed."""
    fields = dict(BUS_FIELDS[which])
    kind = fields["kind"]
    if change[0] == "drop":
        required = [k for k in ("kind", "seq", "t_host", "position", "orientation", "device", "state") if k in fields]
        del fields[required[change[1] % len(required)]]
    elif change[0] == "extra":
        if change[1] in fields:
            return
        fields[change[1]] = change[2]
    else:
        keys = NUMERIC_KEYS[kind]
        fields[keys[change[1] % len(keys)]] = change[2]
    with pytest.raises(MalformedMessage):
        messages.decode([messages.topic(BUS_MESSAGES[which], "dev"), msgspec.msgpack.encode(fields)])


@fuzz(
    200,
    which=st.integers(0, 2),
    value=st.one_of(
        st.floats().filter(lambda x: not abs(x) <= 1e9),
        st.integers(-(2**63), 2**64 - 1).filter(lambda n: not abs(n) <= 2**62),
    ),
)
def test_bus_non_finite_and_out_of_range_numbers_are_malformed(which, value):
    """NaN, inf, |coordinate| > 1e9 and |time| > 2**62 are refused, never passed on or clamped."""
    fields = dict(BUS_FIELDS[which])
    if isinstance(value, float):
        vector = "C" if fields["kind"] == "gaze" else "orientation"
        fields[vector] = [value, *fields.get(vector, [0.0, 0.0])[-2:]]
    else:
        fields["t_host"] = value
    with pytest.raises(MalformedMessage):
        messages.decode([messages.topic(BUS_MESSAGES[which], "dev"), msgspec.msgpack.encode(fields)])


@fuzz(
    200,
    version=st.one_of(
        st.integers(-(2**63), 2**64 - 1).filter(lambda v: v != messages.SCHEMA_VERSION),
        st.floats(),
        st.booleans(),
        st.text(max_size=4),
        st.none(),
        st.lists(st.integers(0, 9), max_size=2),
    ),
)
def test_bus_unknown_schema_versions_are_malformed(version):
    """Any schema version but the integer SCHEMA_VERSION (also 1.0 and true) is refused, as is none at all."""
    fields = {**BUS_FIELDS[0], "v": version}
    if version is None:
        del fields["v"]
    with pytest.raises(MalformedMessage, match="schema version"):
        messages.decode([b"gaze.dev", msgspec.msgpack.encode(fields)])


LENGTH_HEADERS = {  # msgpack type byte -> struct of its 32-bit length (ext adds a type byte)
    b"\xdf": ">I",  # map 32
    b"\xdd": ">I",  # array 32
    b"\xdb": ">I",  # str 32
    b"\xc6": ">I",  # bin 32
    b"\xc9": ">Ib",  # ext 32
}


@fuzz(
    200,
    header=st.sampled_from(sorted(LENGTH_HEADERS)),
    claimed=st.integers(2**16, 2**32 - 1),
    nested=st.booleans(),
)
def test_bus_length_headers_larger_than_the_payload_are_refused_without_allocating(header, claimed, nested):
    """A msgpack map, array, string, binary or ext claiming up to 2**32 - 1 elements in a payload of a few bytes is
    refused by the decoder's length check: no allocation beyond a few payload sizes (no MemoryError path)."""
    fmt = LENGTH_HEADERS[header]
    body = header + struct.pack(fmt, claimed, *([1] if fmt.endswith("b") else [])) + b"\x00" * 8
    payload = (b"\x82\xa1v\x01\xa4kind" + body) if nested else body
    tracemalloc.start()
    try:
        with pytest.raises(MalformedMessage):
            messages.decode([b"gaze.dev", payload])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 * messages.MAX_PAYLOAD_BYTES


@fuzz(50, depth=st.integers(20_000, messages.MAX_PAYLOAD_BYTES - 16), kind=st.sampled_from([b"\x91", b"\x81\xa1k"]))
def test_bus_payload_nested_deeper_than_msgspec_follows_is_malformed(depth, kind):
    """Regression: arrays or maps nested thousands deep raised RecursionError out of decode (it would have
    killed the compositor's ingest thread); now MalformedMessage."""
    payload = b"\x82\xa1v\x01\xa1x" + kind * (depth // len(kind)) + b"\x01"
    if len(payload) > messages.MAX_PAYLOAD_BYTES:
        return
    with pytest.raises(MalformedMessage, match="nested too deeply"):
        messages.decode([b"gaze.dev", payload])


def test_bus_oversized_payload_and_topic_are_refused_before_decoding():
    """Payloads over MAX_PAYLOAD_BYTES and topics over MAX_TOPIC_BYTES are refused by their size alone."""
    with pytest.raises(MalformedMessage, match="exceeds"):
        messages.decode([b"gaze.dev", b"\xc1" * (messages.MAX_PAYLOAD_BYTES + 1)])
    with pytest.raises(MalformedMessage, match="exceeds"):
        messages.decode([b"gaze." + b"d" * messages.MAX_TOPIC_BYTES, BUS_FRAMES[0][1]])
    longest = b"status." + b"d" * (messages.MAX_TOPIC_BYTES - len(b"status."))
    assert messages.decode([longest, BUS_FRAMES[3][1]])[1] == longest.decode()[len("status.") :]


# --- SMI iView X lines: drivers.protocols.smi and smi:// -----------------------------------------------------

SMI_FORMATS = [smi.SampleFormat.parse(text) for text in (smi.GAZE_FORMAT, *smi.RED_FORMATS)]
SMI_LINES = [
    "ET_SPL 102172364740 b 855 855 346 346 13.103793 11.830818 13.103793 11.830818 -66.588 -2.985 18.302 11.463 "
    "582.493 574.155 346.478830 623.560946 432.144375 461.448565",
    "ET_SPL b 100527788 790 790 255 255 -59.923  3.225 14.816 17.588 587.446 580.656",
    "ET_SPL 1001 l 591 732",
    "ET_FIX l 100527771763 512.0 384.0",
    "ET_EFX l 100527771763 100527971763 200 512.0 384.0",
    "ET_VLS l 640 512 0.5 0.3\u00b0 0.4\u00b0",
    'ET_FRM "%TU %ET %SX %SY"',
    "ET_SRT 250",
]
SMI_WORDS = st.sampled_from(
    ["ET_SPL", "ET_FIX", "ET_EFX", "ET_VLS", "ET_SRT", "b", "l", "r", "0", "1", "-2.5", ".5", "1.", "1e308", "1e999"]
    + ["nan", "inf", "-", "+", '"', '"x y"', "\u00b0", "\t", "1" * 40, "%TU", "%ET", "%SX", "%XX", ":", ","]
)
SMI_TEXT = st.one_of(
    st.lists(SMI_WORDS, max_size=24).map(" ".join),
    st.text(max_size=200),
    st.sampled_from(SMI_LINES).flatmap(
        lambda line: mutations(line.encode("latin-1")).map(lambda b: b.decode("latin-1"))
    ),
)


def smi_outcome(data: bytes) -> None:
    """Every SMI decoding step on one datagram: each returns a well-formed value or raises SmiError."""
    try:
        text = smi.decode(data)
    except smi.SmiError:
        return
    for step in (smi.parse_line, smi.parse_event, smi.Validation.parse, smi.SampleFormat.parse):
        try:
            step(text)
        except smi.SmiError:
            pass
    try:
        smi.int_args(tuple(text.split()), 0, 10**6, (1, 2, 3))
    except smi.SmiError:
        pass
    for fmt in SMI_FORMATS:
        try:
            sample = fmt.parse_line(text)
        except smi.SmiError:
            continue
        for name, value in sample.values.items():
            if name in smi.COUNTERS:
                assert isinstance(value, int) and 0 <= value <= smi.MAX_COUNTER
            else:
                assert all(math.isfinite(v) for v in value) and len(value) == (2 if sample.eye == "b" else 1)


@fuzz(400, data=st.binary(max_size=smi.MAX_LINE_BYTES))
def test_smi_any_datagram_parses_or_raises_smi_error(data):
    """Arbitrary datagrams up to MAX_LINE_BYTES: every decoding step gives a finite value or SmiError."""
    smi_outcome(data)


@fuzz(400, text=SMI_TEXT)
def test_smi_near_miss_lines_parse_or_raise_smi_error(text):
    """Lines built from the grammar's own words, and mutations of the section 7 vectors, parse or raise SmiError."""
    smi_outcome(text.encode("latin-1", "replace"))


@pytest.mark.parametrize(
    "line",
    [
        "ET_SPL 1 b " + "1" * 4000 + "x",
        "ET_SPL 1 b 1 " + "1" * 4000 + "e",
        "ET_SPL b 1 1 1 1 1 " + "1" * 4000 + " x",
        "ET_SPL 1 l 1." + "1" * 4000 + "+",
    ],
)
def test_smi_long_digit_runs_are_refused_in_linear_time(line):
    """Regression: a number pattern with two ways to split a run of digits took about 2 s per 4 KB datagram
    (quadratic backtracking) before failing; now every format refuses such a line in milliseconds."""
    start = time.perf_counter()
    for fmt in SMI_FORMATS:
        with pytest.raises(smi.SmiError):
            fmt.parse_line(line)
    assert time.perf_counter() - start < 0.25


class ScriptedTracker:
    """An iView X on a loopback UDP port that answers the driver's handshake (ET_PNG, ET_SRT) and otherwise sends
    only what the test gives it."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.05)
        self.address = self.sock.getsockname()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while not self._stop.is_set():
            try:
                data, addr = self.sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            reply = {b"ET_PNG": b"ET_PNG\n", b"ET_SRT": b"ET_SRT 250\n"}.get(data.strip())
            if reply:
                self.sock.sendto(reply, addr)

    def send(self, data: bytes, to: tuple[str, int]) -> None:
        self.sock.sendto(data, to)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.sock.close()


BAD_TOKENS = ["x", "1.5.5", "--1", "nan", "inf", "1e999", "q"]
SMI_BAD_DATAGRAMS = st.one_of(
    st.binary(max_size=200).filter(lambda b: not b.strip(b" \t\r\n").startswith(b"ET_")),  # not a mnemonic
    st.tuples(st.sampled_from(SMI_LINES[:3]), st.sampled_from(sorted(set(range(32)) - {9}) + [127])).map(
        lambda t: (t[0][:9] + chr(t[1]) + t[0][9:]).encode("latin-1")  # a control character inside
    ),
    st.tuples(st.lists(st.sampled_from(["1", "b", "l", "2.5", "-3"]), max_size=8), st.sampled_from(BAD_TOKENS)).map(
        lambda t: ("ET_SPL " + " ".join([*t[0], t[1]])).encode()  # a sample no format can match
    ),
    st.integers(smi.MAX_LINE_BYTES + 1, 2 * smi.MAX_LINE_BYTES).map(lambda n: b"ET_SPL " + b"1" * (n - 7)),
)


def test_smi_driver_counts_each_refused_datagram_once_and_keeps_streaming():
    """Over a real UDP socket, every refused datagram raises the driver's malformed count by exactly one, events
    and replies are not counted, nothing escapes read(), and the samples that follow are published."""
    tracker = ScriptedTracker()
    good = [SMI_LINES[3].encode(), b"ET_CSZ 1280 1024"]

    @settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(bad=st.lists(SMI_BAD_DATAGRAMS, min_size=1, max_size=12), t_us=st.integers(1, 2**40))
    def check(bad, t_us):
        driver = open_driver(f"smi://127.0.0.1:{tracker.address[1]}?listen=0")
        driver.open()
        try:
            for data in [*bad, *good, f"ET_SPL {t_us} b 600 610 300 310".encode()]:
                tracker.send(data, driver.local_address)
            samples = collect(driver, lambda s: any(x.t_dev == t_us * 1000 for x in s))
        finally:
            driver.close()
        assert [s.t_dev for s in samples] == [t_us * 1000]
        assert driver.counters.malformed == len(bad)
        for s in samples:
            publishable(s)

    try:
        check()
    finally:
        tracker.close()


def test_smi_driver_classifies_a_sample_line_by_its_parsed_mnemonic():
    """Regression: a line whose mnemonic followed other whitespace (NEL, NBSP) passed parse_line but not the
    driver's startswith("ET_SPL"), so a bad sample line was ignored without being counted; now the parsed
    mnemonic decides and such a line is a sample (or counted as malformed)."""
    tracker = ScriptedTracker()
    driver = open_driver(f"smi://127.0.0.1:{tracker.address[1]}?listen=0")
    driver.open()
    try:
        for data in (b"\x85ET_SPL 5 b 1 2", b"\xa0ET_SPL 6 b 600 610 300 310", b"ET_SPL 7 b 600 610 300 310"):
            tracker.send(data, driver.local_address)
        samples = collect(driver, lambda s: any(x.t_dev == 7000 for x in s))
    finally:
        driver.close()
        tracker.close()
    assert [s.t_dev for s in samples] == [6000, 7000]
    assert driver.counters.malformed == 1


# --- FOVE frames: drivers.protocols.fove and fove:// ---------------------------------------------------------

FOVE_EYE = fove.Eye(
    id=1,
    timestamp=8333,
    gaze_left=(0.0, 0.0, 1.0),
    gaze_right=(0.0, 0.0, 1.0),
    state_left=1,
    state_right=1,
    ray_origin=(0.0, 0.0, 0.0),
    ray_direction=(0.0, 0.0, 1.0),
    depth=1.5,
    result=0,
)
FOVE_POSE = fove.Pose(id=1, timestamp=14286, orientation=(0.0, 0.0, 0.0, 1.0), position=(0.0, 0.0, 0.0))
FOVE_RECORDS = [FOVE_EYE, FOVE_POSE, fove.Hello(fove.API_VERSION, 8), fove.Subscribe(8)]
FOVE_PAYLOADS = [fove.encode(r)[4:] for r in FOVE_RECORDS]
FOVE_KEYS = sorted({k for r in FOVE_RECORDS for k in r.__struct_fields__} | {"type"})


def fove_outcome(payload: bytes) -> fove.Record | None:
    try:
        record = fove.decode(payload)
    except fove.FrameError:
        return None
    assert fove.decode(fove.encode(record)[4:]) == record
    return record


@fuzz(300, payload=st.binary(max_size=200))
def test_fove_any_payload_is_a_record_or_frame_error(payload):
    """Arbitrary payloads decode to a record that round-trips, or raise FrameError."""
    fove_outcome(payload)


@fuzz(300, payload=st.sampled_from(FOVE_PAYLOADS).flatmap(mutations))
def test_fove_corrupted_records_are_records_or_frame_errors(payload):
    """Valid hello, subscribe, eye and pose payloads, corrupted, decode or raise FrameError."""
    fove_outcome(payload)


@fuzz(
    300,
    fields=st.fixed_dictionaries(
        {"type": st.sampled_from(["eye", "pose", "hello", "subscribe", "gossip"])},
        optional={k: MSGPACK_VALUES for k in FOVE_KEYS if k != "type"},
    ),
)
def test_fove_records_with_wrong_types_are_frame_errors(fields):
    """Maps with the records' own keys holding arbitrary values decode to a valid record or raise FrameError;
    a decoded record holds only finite numbers within 1e6."""
    record = fove_outcome(msgspec.msgpack.encode(fields))
    if isinstance(record, fove.Eye | fove.Pose):
        vectors = [getattr(record, k) for k in record.__struct_fields__ if isinstance(getattr(record, k), tuple)]
        assert all(math.isfinite(c) and abs(c) <= 1e6 for v in vectors for c in v)


@fuzz(50, depth=st.integers(20_000, fove.MAX_FRAME_BYTES - 64), key=st.sampled_from(["api_version", "gossip"]))
def test_fove_values_nested_deeper_than_msgspec_follows_are_frame_errors(depth, key):
    """Regression: a deeply nested value placed before "type" raised RecursionError out of fove.decode (the
    driver and the emulator let it escape); now FrameError."""
    payload = b"\x82" + msgspec.msgpack.encode(key) + b"\x91" * depth + b"\x01\xa4type\xa5hello"
    with pytest.raises(fove.FrameError, match="nested too deeply"):
        fove.decode(payload)


@fuzz(300, stream=st.binary(max_size=600), cuts=st.lists(st.integers(0, 600), max_size=8))
def test_fove_frame_reader_splits_any_stream_or_refuses_an_oversize_header(stream, cuts):
    """Any byte stream fed in any chunking yields payloads that, with their length prefixes, are exactly the
    stream's start, or raises FrameTooLarge at a header announcing more than MAX_FRAME_BYTES."""
    reader, payloads = fove.FrameReader(), []
    bounds = [0, *sorted(cuts), len(stream)]
    try:
        for a, b in zip(bounds, bounds[1:], strict=False):
            payloads += reader.feed(stream[a:b])
    except fove.FrameTooLarge:
        framed = b"".join(struct.pack(">I", len(p)) + p for p in payloads)
        assert struct.unpack_from(">I", stream, len(framed))[0] > fove.MAX_FRAME_BYTES
        return
    framed = b"".join(struct.pack(">I", len(p)) + p for p in payloads)
    assert stream.startswith(framed) and len(stream) - len(framed) < 4 + fove.MAX_FRAME_BYTES


@settings(max_examples=8, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    bad=st.lists(
        st.one_of(
            st.binary(max_size=64),
            st.sampled_from(FOVE_PAYLOADS[2:]),  # records a server must not send mid-stream
            st.sampled_from(FOVE_PAYLOADS[:2]).flatmap(mutations),
        ),
        max_size=10,
    )
)
def test_fove_driver_counts_each_refused_frame_once_and_publishes_only_bus_ready_samples(bad):
    """Over a real TCP socket, every frame that is not a valid eye or pose record raises malformed by exactly one
    (the codec's verdict), nothing escapes read(), and every published sample survives the bus decoder."""
    expected_bad = sum(not isinstance(fove_outcome(p), fove.Eye | fove.Pose) for p in bad)
    last = msgspec.structs.replace(FOVE_EYE, id=99, timestamp=99_000)
    script = [struct.pack(">I", len(p)) + p for p in bad] + [fove.encode(last)]
    with ScriptedFoveServer(script) as server:
        driver = FoveDriver(server.url)
        driver.open()
        samples = collect(driver, lambda s: any(x.t_dev == 99_000_000 for x in s))
        driver.close()
    assert samples[-1].t_dev == 99_000_000
    assert driver.counters.malformed == expected_bad
    for s in samples:
        publishable(s, "fove")


def test_fove_driver_counts_times_beyond_the_bus_range_as_malformed():
    """Regression: an eye or pose record with a u64 microsecond timestamp past 2**62 ns (valid on the FOVE wire)
    became a sample the bus could not carry: past 2**64 ns msgspec raised OverflowError out of the driver
    host's publish; now such a record is counted as malformed."""
    script = [
        fove.encode(msgspec.structs.replace(FOVE_EYE, id=1, timestamp=2**64 - 1)),
        fove.encode(msgspec.structs.replace(FOVE_POSE, id=1, timestamp=2**62 // 1000 + 1)),
        fove.encode(msgspec.structs.replace(FOVE_EYE, id=2, timestamp=2**62 // 1000)),
    ]
    with ScriptedFoveServer(script) as server:
        driver = FoveDriver(server.url)
        driver.open()
        samples = collect(driver, at_least(1))
        driver.close()
    assert [s.seq for s in samples] == [2] and driver.counters.malformed == 2
    publishable(samples[0], "fove")


# --- HID reports: drivers.protocols.dk2 and hid:// ------------------------------------------------------------

DK2_DECODERS = [dk2.decode_dk2_report, dk2.decode_dk1_report, dk2.decode_keep_alive, dk2.decode_config]
DK2_IDS = [dk2.DK2_SENSOR_ID, dk2.DK1_SENSOR_ID, dk2.KEEP_ALIVE_ID, dk2.CONFIG_ID]


@fuzz(
    400,
    data=st.one_of(
        st.binary(max_size=80),
        st.tuples(st.sampled_from(DK2_IDS), st.sampled_from([5, 6, 7, 61, 62, 63, 64, 65])).flatmap(
            lambda t: st.binary(min_size=t[1] - 1, max_size=t[1] - 1).map(lambda b, i=t[0]: bytes([i]) + b)
        ),
    ),
)
def test_dk2_any_report_decodes_or_raises_dk2_format_error(data):
    """Every HID report decoder takes any bytes: a report of in-range fields, or Dk2FormatError."""
    for decode in DK2_DECODERS:
        try:
            report = decode(data)
        except dk2.Dk2FormatError:
            continue
        if isinstance(report, dk2.Dk2SensorReport):
            assert dk2.decode_dk2_report(dk2.encode_dk2_report(report)) == report  # every field kept
            assert dk2.encode_dk2_report(report)[:12] == data[:12] and dk2.encode_dk2_report(report)[44:] == data[44:]
            assert all(-(2**20) <= c < 2**20 for s in report.slots for c in (*s.accel, *s.gyro))
    try:
        vector = dk2.decode_vector(data)
    except dk2.Dk2FormatError:
        return
    assert dk2.encode_vector(vector)[:7] == data[:7]


DK2_REPORTS = st.one_of(
    st.binary(min_size=dk2.DK2_SENSOR_SIZE - 1, max_size=dk2.DK2_SENSOR_SIZE - 1).map(lambda b: b"\x0b" + b),
    st.binary(min_size=1, max_size=dk2.DK2_SENSOR_SIZE),  # mostly the wrong size or id
)


@fuzz(40, reports=st.lists(DK2_REPORTS, min_size=1, max_size=24))
def test_hid_driver_turns_any_report_into_a_unit_pose_or_counts_it(reports):
    """Through the real adapter and driver (hid://stub, its queue filled with arbitrary reports): each report of
    the wrong size or id raises malformed by one, each 0x0B report with samples gives one finite unit-quaternion
    pose that survives the bus decoder, and nothing escapes read() (fused IMU values at the 21-bit extremes)."""
    driver = HidDriver("hid://stub", VirtualClock(10**9))
    driver.open()
    driver.hid._queue.extend(reports)  # what the device sends next (the stub's clock stands still: nothing else)
    poses = driver.read(0.0)
    driver.close()
    sensor = [r for r in reports if len(r) == dk2.DK2_SENSOR_SIZE and r[0] == dk2.DK2_SENSOR_ID]
    assert driver.counters.malformed == len(reports) - len(sensor)
    assert len(poses) == sum(r[3] > 0 for r in sensor)  # num_samples
    for pose in poses:
        assert abs(np.linalg.norm(pose.orientation) - 1.0) < 1e-6
        publishable(pose, "hid")


# --- serial lines and frames: drivers.protocols.razor, hatire, framing, and serial:// --------------------------

RAZOR_FRAMES = st.one_of(
    st.tuples(st.floats(-180, 180), st.floats(-90, 90), st.floats(-180, 180)).map(lambda a: razor.encode_ypr(*a)),
    st.text(alphabet=[chr(c) for c in range(0x21, 0x7F) if chr(c) not in "#!"], max_size=16).map(razor.encode_synch),
)
HATIRE_FRAMES = st.builds(
    lambda cpt, a: hatire.encode_frame(hatire.HatireFrame(cpt, *a)),
    st.integers(0, hatire.COUNTER_WRAP - 1),
    st.tuples(*[st.floats(-360, 360, width=32)] * 3),
)


def feed_in_chunks(framer, stream: bytes, cuts: list[int]) -> list:
    bounds = [0, *sorted(c % (len(stream) + 1) for c in cuts), len(stream)]
    return [f for a, b in zip(bounds, bounds[1:], strict=False) for f in framer.feed(stream[a:b])]


@fuzz(
    200,
    parts=st.lists(
        st.tuples(RAZOR_FRAMES, st.binary(max_size=40).map(lambda b: bytes(c for c in b if c not in b"#!\n"))),
        max_size=8,
    ),
    cuts=st.lists(st.integers(0, 10**6), max_size=6),
)
def test_razor_framer_returns_every_frame_and_counts_exactly_the_garbage_between(parts, cuts):
    """Valid Razor lines with garbage after each, fed in any chunking, come back in order and decoded, and
    `discarded` counts exactly the garbage bytes."""
    stream = b"".join(frame + garbage for frame, garbage in parts)
    framer = razor.RazorFramer()
    frames = feed_in_chunks(framer, stream, cuts)
    assert frames == [razor.decode_line(frame) for frame, _ in parts]
    assert framer.discarded == sum(len(garbage) for _, garbage in parts)


@fuzz(
    200,
    parts=st.lists(
        st.tuples(HATIRE_FRAMES, st.binary(max_size=40).map(lambda b: bytes(c for c in b if c != 0xAA))), max_size=8
    ),
    cuts=st.lists(st.integers(0, 10**6), max_size=6),
)
def test_hatire_framer_returns_every_frame_and_counts_exactly_the_garbage_between(parts, cuts):
    """Valid HATIRE frames with garbage after each, fed in any chunking, come back in order, and `discarded`
    counts exactly the garbage bytes."""
    stream = b"".join(frame + garbage for frame, garbage in parts)
    framer = hatire.HatireFramer()
    frames = feed_in_chunks(framer, stream, cuts)
    assert frames == [hatire.decode_frame(frame) for frame, _ in parts]
    assert framer.discarded == sum(len(garbage) for _, garbage in parts)


@fuzz(300, stream=st.binary(max_size=400), cuts=st.lists(st.integers(0, 10**6), max_size=6))
def test_serial_framers_take_any_bytes_and_hold_at_most_one_unfinished_frame(stream, cuts):
    """Arbitrary bytes in any chunking give only valid frames (finite angles in range), never an exception, and
    each framer keeps at most one unfinished frame's bytes."""
    for framer, held in ((razor.RazorFramer(), razor.MAX_LINE), (hatire.HatireFramer(), hatire.FRAME_SIZE - 1)):
        for frame in feed_in_chunks(framer, stream, cuts):
            if isinstance(frame, razor.Ypr):
                razor.check_angles(frame.yaw, frame.pitch, frame.roll)
            elif isinstance(frame, hatire.HatireFrame):
                assert all(math.isfinite(a) and abs(a) <= 360 for a in (frame.yaw, frame.pitch, frame.roll))
        assert framer.discarded <= len(stream) and len(framer._buf) <= held


@fuzz(300, line=st.one_of(st.binary(max_size=200), RAZOR_FRAMES.flatmap(mutations)))
def test_razor_any_line_decodes_or_raises_razor_format_error(line):
    """decode_line and parse_commands take any bytes: a frame with angles in range, or RazorFormatError; commands
    and an unfinished tail shorter than the longest command."""
    try:
        frame = razor.decode_line(line)
    except razor.RazorFormatError:
        frame = None
    if isinstance(frame, razor.Ypr):
        razor.check_angles(frame.yaw, frame.pitch, frame.roll)
    commands, tail = razor.parse_commands(line)
    assert len(tail) < 5 and all(c.isascii() for c in commands)


@fuzz(300, data=st.one_of(st.binary(max_size=40), HATIRE_FRAMES.flatmap(mutations)))
def test_hatire_any_frame_decodes_or_raises_hatire_format_error(data):
    """decode_frame takes any bytes: a data frame with finite angles within 360 degrees, an info frame, or
    HatireFormatError."""
    try:
        frame = hatire.decode_frame(data)
    except hatire.HatireFormatError:
        return
    if isinstance(frame, hatire.HatireFrame):
        assert all(math.isfinite(a) and abs(a) <= 360 for a in (frame.yaw, frame.pitch, frame.roll))


@settings(max_examples=10, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    protocol=st.sampled_from(["razor", "hatire"]),
    garbage=st.lists(st.binary(min_size=1, max_size=30), min_size=1, max_size=5),
    data=st.data(),
)
def test_serial_driver_counts_every_garbage_byte_once_over_loop(protocol, garbage, data):
    """serial:// over pyserial's loop://: garbage between frames raises malformed by exactly its length (plus the
    echoed start command), the frames still become poses that survive the bus decoder."""
    frames_st, marks = (RAZOR_FRAMES, b"#!\n") if protocol == "razor" else (HATIRE_FRAMES, b"\xaa")
    frames = [data.draw(frames_st) for _ in garbage]
    garbage = [bytes(c for c in g if c not in marks) for g in garbage]
    last = razor.encode_ypr(1.0, 2.0, 3.0) if protocol == "razor" else hatire.encode_frame(HatireFrame(5, 1, 2, 3))
    driver = open_driver(f"serial://?port=loop://&protocol={protocol}")
    driver.open()
    driver.port.write(b"".join(g + f for g, f in zip(garbage, frames, strict=True)) + last)
    angles = [f for f in [*frames, last] if protocol == "hatire" or f.startswith(b"#YPR")]
    poses = collect(driver, at_least(len(angles)), 5.0)
    driver.close()
    assert len(poses) == len(angles)
    assert driver.counters.malformed == len(SERIAL_PROTOCOLS[protocol][1]) + sum(map(len, garbage))  # echo: start
    for pose in poses:
        publishable(pose, "serial")


# --- Pupil Core datums: drivers.pupil --------------------------------------------------------------------------

PUPIL_TOPICS = st.sampled_from([b"gaze.3d.01.", b"gaze.3d.0.", b"gaze.3d.1.", b"gaze.3d.2.", b"pupil.0.3d", b""])
PUPIL_NUMBERS = st.one_of(st.floats(), st.floats(-1e9, 1e9), st.integers(-(2**63), 2**63))
PUPIL_VECTORS = st.one_of(st.lists(PUPIL_NUMBERS, min_size=2, max_size=4), MSGPACK_VALUES)


def pupil_outcome(topic: bytes, payload: bytes) -> Gaze | None:
    """The decoded gaze, which must survive the bus decoder, or None for MalformedDatum."""
    try:
        gaze = decode_gaze(topic, payload)
    except MalformedDatum:
        return None
    publishable(gaze, "pupil")
    assert all(abs(np.linalg.norm(v) - 1.0) < 1e-9 for v in (gaze.C, gaze.L, gaze.R) if v is not None)
    return gaze


@fuzz(
    300,
    topic=PUPIL_TOPICS,
    payload=st.one_of(st.binary(max_size=200), mutations(msgspec.msgpack.encode(SECTION7_GAZE))),
)
def test_pupil_any_message_is_bus_ready_gaze_or_malformed_datum(topic, payload):
    """Arbitrary and corrupted backbone messages decode to unit, bus-ready gaze or raise MalformedDatum."""
    pupil_outcome(topic, payload)


@fuzz(
    400,
    topic=PUPIL_TOPICS,
    changes=st.fixed_dictionaries(
        {},
        optional={
            "confidence": PUPIL_NUMBERS | MSGPACK_VALUES,
            "timestamp": PUPIL_NUMBERS | MSGPACK_VALUES,
            "gaze_point_3d": PUPIL_VECTORS,
            "gaze_normal_3d": PUPIL_VECTORS,
            "gaze_normals_3d": st.dictionaries(st.sampled_from(["0", "1", "2", ""]), PUPIL_VECTORS, max_size=3)
            | MSGPACK_VALUES,
            "base_data": MSGPACK_VALUES,
        },
    ),
)
def test_pupil_datums_with_wrong_or_extreme_values_are_bus_ready_or_malformed(topic, changes):
    """Datums whose fields hold wrong types, NaN, inf, huge or zero vectors decode to bus-ready gaze or raise
    MalformedDatum."""
    pupil_outcome(topic, msgspec.msgpack.encode({**SECTION7_GAZE, **changes}))


def test_pupil_regressions_deep_nesting_and_a_gaze_point_beyond_the_bus_range():
    """Regression: an ignored key nested deeply raised RecursionError out of decode_gaze (and the driver's read);
    a gaze_point_3d over 1e6 m away gave a depth the bus refuses, so the compositor dropped the whole sample.
    Both are MalformedDatum now, counted once each by the driver."""
    deep = b"\x82\xa3xyz" + b"\x91" * 60_000 + b"\x01" + msgspec.msgpack.encode("confidence") + b"\xcb" + bytes(8)
    far = msgspec.msgpack.encode({**SECTION7_GAZE, "gaze_point_3d": [1e9, 1e9, 1e9]})
    with pytest.raises(MalformedDatum, match="nested too deeply"):
        decode_gaze(b"gaze.3d.01.", deep)
    with pytest.raises(MalformedDatum, match="beyond"):
        decode_gaze(b"gaze.3d.01.", far)
    driver = PupilDriver("pupil://127.0.0.1:50020")
    good = [b"gaze.3d.01.", msgspec.msgpack.encode(SECTION7_GAZE)]
    samples = [driver._sample(frames, 0) for frames in ([b"gaze.3d.01.", deep], [b"gaze.3d.01.", far], good, [b"x"])]
    assert [s is not None for s in samples] == [False, False, True, False]
    assert driver.counters.malformed == 3


# --- trace files: replay.trace (JSONL) and replay.formats (EyeLink ASC, CSV, Pupil Player, GazeBaseVR) ---------


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


# --- TOML: configs (hmdrt.configfile, load_config, load_eval_config), profiles and scene descriptions --------


def toml_value(v) -> str:
    """A TOML value (inline tables and arrays) for a Python value."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(map(toml_value, v)) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k, ensure_ascii=False)} = {toml_value(x)}" for k, x in v.items()) + "}"
    return v.isoformat()


def toml_document(doc: dict) -> str:
    return "".join(f"{json.dumps(k, ensure_ascii=False)} = {toml_value(v)}\n" for k, v in doc.items())


def struct_keys(*types) -> list[str]:
    """Every field name of msgspec structs and the structs they hold, with tag names and values."""
    keys, todo = set(), list(types)
    while todo:
        t = todo.pop()
        info = msgspec.inspect.type_info(t)
        stack = [info]
        while stack:
            i = stack.pop()
            if isinstance(i, msgspec.inspect.StructType):
                if i.tag_field:
                    keys |= {i.tag_field, str(i.tag)}
                keys |= {f.name for f in i.fields}
                stack += [f.type for f in i.fields]
            elif isinstance(i, msgspec.inspect.UnionType):
                stack += list(i.types)
            elif isinstance(i, msgspec.inspect.ListType | msgspec.inspect.DictType):
                stack += [i.item_type] if hasattr(i, "item_type") else [i.key_type, i.value_type]
            elif isinstance(i, msgspec.inspect.TupleType | msgspec.inspect.VarTupleType):
                stack += list(getattr(i, "item_types", [getattr(i, "item_type", None)]))
    return sorted(k for k in keys if k)


TOML_SCALARS = st.one_of(
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(),
    st.floats(-100, 100),
    st.text(max_size=10),
    st.sampled_from(["", "left", "rrm", "full", "sim-cpu", "whitted", "0,0", "640x720", "synthetic://?seed=1"]),
    st.dates(),
)


def toml_docs(*types) -> st.SearchStrategy[dict]:
    """TOML documents whose keys are the config types' own field and tag names (and a stray one), holding
    arbitrary values, nested tables and arrays of tables."""
    keys = st.sampled_from([*struct_keys(*types), "stray"])
    values = st.recursive(
        TOML_SCALARS,
        lambda inner: st.lists(inner, max_size=3) | st.dictionaries(keys, inner, max_size=5),
        max_leaves=16,
    )
    return st.dictionaries(keys, values, max_size=8)


def error_names_file(exc: Exception, path: Path) -> None:
    assert str(path) in str(exc) or path.name in str(exc), f"{exc} does not name {path}"


@fuzz(150, doc=toml_docs(RunConfig))
def test_run_config_of_any_toml_is_a_run_config_or_config_error(doc):
    """load_config of any document with the config's own keys is a RunConfig or a ConfigError naming the file."""
    path = scratch("run.toml", toml_document(doc))
    try:
        assert isinstance(load_config(path), RunConfig)
    except ConfigError as exc:
        error_names_file(exc, path)


@pytest.mark.parametrize("value", ["[]", "1", '"x"'])
def test_run_config_whose_run_is_not_a_table_is_a_config_error(value):
    """A config whose `run` is an array, a number or a string is a ConfigError naming the file."""
    path = scratch("run-not-table.toml", f"run = {value}\n")
    with pytest.raises(ConfigError, match="run-not-table.toml"):
        load_config(path)


@fuzz(100, doc=toml_docs(EvalConfig))
def test_eval_config_of_any_toml_is_an_eval_config_or_config_error(doc):
    """load_eval_config of any document with the config's own keys is an EvalConfig or a ConfigError."""
    path = scratch("eval.toml", toml_document(doc))
    try:
        assert isinstance(load_eval_config(path), EvalConfig)
    except ConfigError:
        pass


@fuzz(150, doc=toml_docs(HmdProfile))
def test_profile_of_any_toml_is_a_profile_or_config_error(doc):
    """A .toml profile of any document with the profile's keys is an HmdProfile or a ConfigError naming the file."""
    path = scratch("profile.toml", toml_document(doc))
    try:
        assert isinstance(get_profile(str(path)), HmdProfile)
    except ConfigError as exc:
        error_names_file(exc, path)


@fuzz(100, doc=toml_docs(SceneFile))
def test_scene_description_of_any_toml_is_a_scene_or_scene_error(doc):
    """A TOML scene description of any document with the scene's keys (objects, materials, textures, lights) is a
    Scene or a SceneError naming the file."""
    path = scratch("scene.toml", toml_document(doc))
    try:
        assert isinstance(load_scene_file(path), Scene)
    except SceneError as exc:
        error_names_file(exc, path)


TOML_LOADERS = {
    "config": (lambda p: read_toml(p), ConfigError),
    "run": (lambda p: load_config(p), ConfigError),
    "eval": (lambda p: load_eval_config(p), ConfigError),
    "profile": (lambda p: get_profile(str(p)), ConfigError),
    "scene": (lambda p: load_scene_file(p), SceneError),
}
TOML_SEED = (Path(__file__).parents[1] / "configs" / "default.toml").read_bytes()


@fuzz(
    200,
    loader=st.sampled_from(sorted(TOML_LOADERS)),
    data=st.one_of(st.binary(max_size=300), mutations(TOML_SEED), st.text(max_size=200).map(str.encode)),
)
def test_any_bytes_as_toml_load_or_raise_the_loaders_error_naming_the_file(loader, data):
    """Arbitrary bytes, non-UTF-8 and mutations of configs/default.toml given to every TOML loader give a value
    or the loader's error (ConfigError, SceneError); a syntax error names the file and the line."""
    load, error = TOML_LOADERS[loader]
    path = scratch(f"{loader}.toml", data)
    try:
        load(path)
    except error as exc:
        if "not valid TOML" in str(exc) and "nested" not in str(exc) and "codec" not in str(exc):
            error_names_file(exc, path)
            assert "line" in str(exc) or "end of document" in str(exc)


@pytest.mark.parametrize("loader", sorted(TOML_LOADERS))
@pytest.mark.parametrize("nesting", ["[" * 600 + "]" * 600, "{a = " * 600 + "1" + "}" * 600])
def test_toml_nested_deeper_than_the_parser_follows_is_the_loaders_error(loader, nesting):
    """Regression: a value nested a few hundred arrays or inline tables deep (1 KB) raised RecursionError out
    of every TOML loader; now it is their own error, naming the file."""
    load, error = TOML_LOADERS[loader]
    path = scratch(f"deep-{loader}.toml", f"name = {nesting}\n")
    with pytest.raises(error, match="nested too deeply") as info:
        load(path)
    error_names_file(info.value, path)


@pytest.mark.parametrize("loader", sorted(TOML_LOADERS))
def test_toml_files_are_size_capped_before_reading(loader):
    """A TOML file over MAX_TOML_BYTES (sparse: nothing to read) is refused by size. Regression: configs and
    profiles were read whole whatever their size, and /dev/zero (size 0) was read without end."""
    load, error = TOML_LOADERS[loader]
    path = sparse(f"big-{loader}.toml", MAX_TOML_BYTES + 1)
    with pytest.raises(error, match="larger than") as info:
        load(path)
    error_names_file(info.value, path)
    with pytest.raises(ConfigError, match="larger than"):
        read_toml("/dev/zero")


def test_non_utf8_and_unreadable_profiles_are_config_errors():
    """Regression: a .toml profile that is not UTF-8 raised UnicodeDecodeError out of get_profile; a NUL in a
    profile path (a string in a config) raised ValueError. Both are ConfigErrors naming the file now."""
    path = scratch("latin1.toml", b"name = '\xe9'\n")
    with pytest.raises(ConfigError, match="latin1.toml"):
        get_profile(str(path))
    with pytest.raises(ConfigError, match="profile"):
        get_profile("bad\x00name.toml")


# --- meshes and textures: hmdrt.scene.files ---------------------------------------------------------------------


def mesh_seeds() -> dict[str, bytes]:
    """A small textured-less box in every mesh format trimesh writes."""
    box = trimesh.creation.box()
    return {
        suffix: trimesh.exchange.export.export_mesh(box, None, suffix[1:])
        for suffix in MESH_SUFFIXES
        if suffix != ".gltf"
    }


MESH_SEEDS = {k: v.encode() if isinstance(v, str) else v for k, v in mesh_seeds().items()}


def mesh_outcome(path: Path) -> None:
    """load_mesh_file gives meshes with finite vertices, in-range faces and finite normals, or SceneError."""
    try:
        meshes, _, images = load_mesh_file(path)
    except SceneError as exc:
        error_names_file(exc, path)
        return
    for mesh in meshes:
        assert np.isfinite(mesh.vertices).all()
        assert mesh.faces.size and mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
        assert mesh.normals is None or np.isfinite(mesh.normals).all()
    for image in images.values():
        assert image.ndim == 3 and image.shape[2] == 3 and np.isfinite(image).all()


@fuzz(60, suffix=st.sampled_from(MESH_SUFFIXES), data=st.binary(max_size=300))
def test_mesh_file_of_any_bytes_is_meshes_or_scene_error(suffix, data):
    """Arbitrary bytes under every mesh suffix load as well-formed meshes or raise SceneError naming the file."""
    mesh_outcome(scratch("fuzz" + suffix, data))


@fuzz(100, case=st.sampled_from(sorted(MESH_SEEDS)).flatmap(lambda s: st.tuples(st.just(s), mutations(MESH_SEEDS[s]))))
def test_corrupted_mesh_files_are_meshes_or_scene_error(case):
    """A box in OBJ, PLY, STL, OFF and GLB, truncated or overwritten anywhere (counts, headers, indices), loads
    as well-formed meshes or raises SceneError."""
    suffix, data = case
    mesh_outcome(scratch("mutant" + suffix, data))


def png(width: int, height: int, idat: bytes = b"") -> bytes:
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", idat) + chunk(b"IEND", b"")


def image_seeds() -> list[bytes]:
    """A 4 x 4 image in the formats PIL writes without extra libraries."""
    pixels = PILImage.fromarray((np.arange(48).reshape(4, 4, 3) * 5).astype(np.uint8))
    seeds = []
    for fmt in ("PNG", "JPEG", "GIF", "BMP", "TIFF", "PPM", "TGA"):
        out = io.BytesIO()
        pixels.save(out, fmt)
        seeds.append(out.getvalue())
    return seeds


@fuzz(80, data=st.one_of(st.binary(max_size=200), st.sampled_from(image_seeds()).flatmap(mutations)))
def test_texture_image_of_any_bytes_is_an_image_or_scene_error(data):
    """Arbitrary bytes, and PNG, JPEG, GIF, BMP, TIFF, PPM and TGA images corrupted anywhere, load as a finite
    linear RGB image or raise SceneError."""
    path = scratch("texture.png", data)
    try:
        image = load_image(path)
    except SceneError as exc:
        error_names_file(exc, path)
        return
    assert image.ndim == 3 and np.isfinite(image).all()


@pytest.mark.parametrize(
    "data",
    [
        b"\x89PNG\r\n\x1a\n\x00\x00\x00\x00IHDR",  # found by the extended run
        b"P6\n4 x\n255\n",
        b"P6\n4 4\n0\n",
    ],
)
def test_image_headers_pil_refuses_with_value_error_are_scene_errors(data):
    """Regression: PIL refuses some headers (a truncated PNG IHDR, PPM numbers that are not numbers, a PPM maxval
    of 0) with ValueError, which escaped load_image; now SceneError naming the file."""
    path = scratch("header.img", data)
    with pytest.raises(SceneError, match="header.img"):
        load_image(path)


def test_texture_decompression_bombs_and_corrupt_mesh_textures_are_scene_errors(tmp_path):
    """Regression: a PNG header claiming 20000 x 20000 pixels raised PIL's DecompressionBombError out of
    load_image, and an OBJ whose texture was truncated raised OSError out of load_mesh_file (PIL decodes lazily).
    Both are SceneErrors naming the file now; no pixels are allocated for the bomb."""
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(png(20_000, 20_000))
    tracemalloc.start()
    try:
        with pytest.raises(SceneError, match="bomb.png"):
            load_image(bomb)
        assert tracemalloc.get_traced_memory()[1] < 10**7
    finally:
        tracemalloc.stop()
    for name in ("fuze.obj", "fuze.obj.mtl"):
        (tmp_path / name).write_bytes((MESHES / name).read_bytes())
    (tmp_path / "fuze uv.jpg").write_bytes((MESHES / "fuze uv.jpg").read_bytes()[:20_000])
    with pytest.raises(SceneError, match="fuze.obj"):
        load_mesh_file(tmp_path / "fuze.obj")


def test_files_named_by_scenes_and_meshes_are_size_capped_and_regular(tmp_path):
    """A glTF buffer or a scene texture over the mesh size cap is refused by size (sparse: nothing read), and a
    texture that is a device (/dev/zero, size 0, endless) is refused as not a regular file. Regression: trimesh
    read whatever a mesh file named, whole, and /dev/zero as a texture was read without end."""
    sparse_buffer = tmp_path / "huge.bin"
    with sparse_buffer.open("wb") as f:
        f.truncate(MAX_MESH_BYTES + 1)
    gltf = {
        "asset": {"version": "2.0"},
        "buffers": [{"uri": "huge.bin", "byteLength": 36}],
        "bufferViews": [{"buffer": 0, "byteLength": 36}],
        "accessors": [{"bufferView": 0, "componentType": 5126, "count": 3, "type": "VEC3"}],
        "meshes": [{"primitives": [{"attributes": {"POSITION": 0}}]}],
        "nodes": [{"mesh": 0}],
        "scenes": [{"nodes": [0]}],
    }
    (tmp_path / "m.gltf").write_text(json.dumps(gltf))
    with pytest.raises(SceneError, match="larger than the limit"):
        load_mesh_file(tmp_path / "m.gltf")
    scene = tmp_path / "s.toml"
    for texture, message in (("/dev/zero", "not a regular file"), ("huge.bin", "larger than the limit")):
        scene.write_text(f'[materials.m]\ntexture = {{ kind = "image", image = "{texture}" }}\n')
        with pytest.raises(SceneError, match=message):
            load_scene_file(scene)
    scene.write_text('[materials.m]\ntexture = { kind = "image", image = "a\\u0000b.png" }\n')
    with pytest.raises(SceneError):
        load_scene_file(scene)


def test_trace_paths_with_a_nul_are_config_errors():
    """Regression: replay://a%00b.jsonl (a NUL after unquoting) raised ValueError out of load_trace; now a
    ConfigError."""
    with pytest.raises(ConfigError):
        load_trace("a\x00b.jsonl")


def test_native_trace_writer_lines_are_the_lines_this_module_treats_as_valid():
    """A TraceWriter's sample lines are exactly NATIVE_LINES (so the trace tests' valid lines are real ones)."""
    stream = io.BytesIO()
    writer = TraceWriter(stream)
    writer.header("fuzz")
    for sample in NATIVE_SAMPLES:
        writer.sample(sample)
    assert stream.getvalue().splitlines()[1:] == NATIVE_LINES
