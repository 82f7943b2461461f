"""Fuzzing bytes and text from outside, serial lines and frames (Razor, HATIRE, framing, serial://):
bad input never gets in, never crashes."""

from __future__ import annotations

import math

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hmdrt.drivers import open_driver
from hmdrt.drivers.protocols import hatire, razor
from hmdrt.drivers.protocols.hatire import HatireFrame
from hmdrt.drivers.serial_port import PROTOCOLS as SERIAL_PROTOCOLS
from tests.fuzz.common import (
    fuzz,
    mutations,
    publishable,
)
from tests.helpers import at_least, collect

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
