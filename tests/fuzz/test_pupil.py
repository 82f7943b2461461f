"""Fuzzing bytes and text from outside, Pupil Core datums (drivers.pupil):
bad input never gets in, never crashes."""

from __future__ import annotations

import msgspec
import numpy as np
import pytest
from hypothesis import strategies as st

from hmdrt.bus.messages import Gaze
from hmdrt.drivers.pupil import MalformedDatum, PupilDriver, decode_gaze
from tests.fuzz.common import (
    MSGPACK_VALUES,
    fuzz,
    mutations,
    publishable,
)
from tests.helpers import SECTION7_GAZE

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
