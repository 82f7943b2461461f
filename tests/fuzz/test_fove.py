"""Fuzzing bytes and text from outside, FOVE frames (drivers.protocols.fove, fove://):
bad input never gets in, never crashes."""

from __future__ import annotations

import math
import struct

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hmdrt.drivers.fove import FoveDriver
from hmdrt.drivers.protocols import fove
from tests.fuzz.common import (
    MSGPACK_VALUES,
    fuzz,
    mutations,
    publishable,
)
from tests.helpers import ScriptedFoveServer, at_least, collect

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
