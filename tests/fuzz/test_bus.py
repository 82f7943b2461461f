"""Fuzzing bytes and text from outside, the bus (hmdrt.bus.messages.decode):
bad input never gets in, never crashes."""

from __future__ import annotations

import struct
import tracemalloc

import msgspec
import pytest
from hypothesis import strategies as st

from hmdrt.bus import messages
from hmdrt.bus.messages import ClockEstimate, Gaze, MalformedMessage, Pose, Status
from tests.fuzz.common import (
    MSGPACK_VALUES,
    SCALARS,
    fuzz,
    mutations,
)

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
