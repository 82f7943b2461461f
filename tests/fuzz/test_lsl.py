"""Fuzzing bytes and text from outside, LSL stream meta-data and samples (drivers.protocols.lsl_gaze,
lsl://): bad input never gets in, never crashes. Needs no liblsl: the stream info is XML as liblsl writes it."""

from __future__ import annotations

import xml.etree.ElementTree as ElementTree

import numpy as np
from hypothesis import strategies as st

from hmdrt.bus.messages import Gaze
from hmdrt.drivers.emulators.lsl_source import CHANNEL_COUNT, titta_channels
from hmdrt.drivers.lsl import DEFAULT_PROFILE
from hmdrt.drivers.protocols.lsl_gaze import AXES, ORIGINS, GazeDecoder, MetadataError, gaze_layout, parse_info
from hmdrt.optics import get_profile
from tests.fuzz.common import fuzz, mutations, publishable

PROFILE = get_profile(DEFAULT_PROFILE)
TYPES = ["Screen", "Direction", "Intersection", "Pupil", "Position"]
KINDS = [t + a for t in TYPES for a in "XYZ"] + ["Confidence", "ValidFlag", "AvailableFlag", "Diameter", ""]
TEXT = st.text(st.characters(blacklist_categories=("Cs", "Cc")), max_size=12)  # what XML can carry
WORDS = st.one_of(st.sampled_from(KINDS), TEXT)
EYES = st.one_of(st.sampled_from(["left", "right", "both", "Left", ""]), st.sampled_from(["binocular", "x"]))
UNITS = st.one_of(st.sampled_from(["mm", "m", "cm", "pixels", "normalized", "bool", "MM", ""]), TEXT)
CHANNEL = st.fixed_dictionaries(
    {"label": TEXT}, optional={"eye": EYES, "type": WORDS, "metatype": WORDS, "unit": UNITS}
)
GROUP = st.builds(  # the channels of one vector, mostly complete: what makes a layout
    lambda base, eye, unit, n, key: [{"label": base + a, "eye": eye, key: base + a, "unit": unit} for a in "XYZ"[:n]],
    st.sampled_from(TYPES),
    st.sampled_from(["left", "right", "both"]),
    st.sampled_from(["mm", "m", "pixels", "normalized", "px", "deg"]),
    st.sampled_from([3, 3, 2, 1]),
    st.sampled_from(["type", "type", "metatype"]),
)
RAY = st.builds(  # a gaze point with its origin, in the eye's order
    lambda eye, origin, units: [
        {"label": f"{base}{a}", "eye": eye, "type": f"{base}{a}", "unit": unit}
        for base, unit in zip(("Intersection", origin), units, strict=True)
        for a in "XYZ"
    ],
    st.sampled_from(["left", "right", "both"]),
    st.sampled_from(["Pupil", "Position"]),
    st.tuples(st.sampled_from(["mm", "m", "cm", "px"]), st.sampled_from(["mm", "m", "cm"])),
)
CHANNELS = st.lists(st.one_of(CHANNEL.map(lambda c: [c]), GROUP, RAY), max_size=6).map(
    lambda groups: [c for group in groups for c in group]
)
VALUES = st.one_of(
    st.floats(),
    st.floats(-2.0, 2.0),
    st.floats(-1e4, 1e4),
    st.sampled_from([0.0, 1.0, float("nan"), float("inf"), 1e9, 1.0000001e9, 1e300]),
)


def info_xml(channels: list[dict[str, str]], count: int, fmt: str = "double64", rate: str = "120") -> bytes:
    """A stream info as liblsl writes it (StreamInfo.as_xml()), describing `channels`."""
    root = ElementTree.Element("info")
    for tag, text in (("name", "fuzz"), ("type", "Gaze"), ("channel_count", str(count)), ("channel_format", fmt)):
        ElementTree.SubElement(root, tag).text = text
    ElementTree.SubElement(root, "source_id").text = "fuzz"
    ElementTree.SubElement(root, "nominal_srate").text = rate
    described = ElementTree.SubElement(ElementTree.SubElement(root, "desc"), "channels")
    for channel in channels:
        element = ElementTree.SubElement(described, "channel")
        for key, value in channel.items():
            ElementTree.SubElement(element, key).text = value
    return ElementTree.tostring(root)


TITTA = info_xml([dict(zip(("label", "eye", "type", "unit"), c, strict=True)) for c in titta_channels()], 37)
TITTA_DECODER = GazeDecoder(gaze_layout(parse_info(TITTA)), profile=PROFILE)


def outcome(data: bytes | str, rows: list[list[float]], axes: str = "head", origin: str = "top-left") -> None:
    """Parse and lay out: MetadataError or a layout, whose decoding of `rows` (repeated to its width) is bus-ready."""
    try:
        layout = gaze_layout(parse_info(data))
    except MetadataError as exc:
        assert str(exc)
        return
    count = layout.meta.channel_count
    bus_ready(GazeDecoder(layout, axes, PROFILE, origin), [(row * count)[:count] for row in rows])


def bus_ready(decoder: GazeDecoder, rows: list[list[float]]) -> None:
    """Every row decodes to None (malformed) or to unit directions that make a gaze the bus takes unchanged."""
    for row in decoder.decode(np.array(rows, dtype=np.float64)):
        if row is None:
            continue
        gaze = Gaze(seq=0, t_host=0, valid=row.valid, C=row.C, L=row.L, R=row.R, depth_m=row.depth_m)
        publishable(gaze)
        for v in (row.C, row.L, row.R):
            assert v is None or abs(np.linalg.norm(v) - 1.0) < 1e-9
        assert row.valid == any(v is not None for v in (row.C, row.L, row.R))


@fuzz(
    200,
    data=st.one_of(st.binary(max_size=300), mutations(TITTA)),
    rows=st.lists(st.lists(VALUES, min_size=1), max_size=3),
)
def test_lsl_any_stream_info_is_a_layout_or_metadata_error(data, rows):
    """Arbitrary and corrupted stream info XML parses to a layout or raises MetadataError, never anything else."""
    outcome(data, rows or [[0.0]])


@fuzz(
    300,
    channels=CHANNELS,
    extra=st.integers(0, 3),
    fmt=st.sampled_from(["double64"] * 4 + ["float32", "int16", "string", ""]),
    rate=st.sampled_from(["120", "0", "-5", "nan", "1e400", "x"]),
    rows=st.lists(st.lists(VALUES, min_size=1, max_size=16), min_size=1, max_size=4),
    axes=st.sampled_from(list(AXES)),
    origin=st.sampled_from(ORIGINS),
)
def test_lsl_channel_descriptions_and_samples_are_bus_ready_or_refused(channels, extra, fmt, rate, rows, axes, origin):
    """Any mix of labels, eyes, types (also as `metatype`) and units gives a layout or one MetadataError, and then
    any sample values (NaN, inf, huge, zero vectors) give unit, bus-ready gaze or a malformed row."""
    outcome(info_xml(channels, max(len(channels) + extra, 1), fmt, rate), rows, axes, origin)


@fuzz(200, rows=st.lists(st.lists(VALUES, min_size=CHANNEL_COUNT, max_size=CHANNEL_COUNT), min_size=1, max_size=4))
def test_lsl_tittalsl_samples_with_any_values_are_bus_ready_or_malformed(rows):
    """TittaLSL's layout with any channel values: unit, bus-ready gaze or a malformed row."""
    bus_ready(TITTA_DECODER, rows)


def test_lsl_regressions_oversized_entities_and_deep_nesting():
    """Stream info over the size cap, with a DTD (entity expansion), nested deeply or with a huge channel count is
    one MetadataError each."""
    for data, message in (
        (b"<info>" + b" " * 600_000 + b"</info>", "exceeds"),
        (b'<!DOCTYPE info [<!ENTITY a "aaaa">]><info><name>&a;</name></info>', "DTD"),
        (b"<info>" + b"<a>" * 50_000 + b"</a>" * 50_000 + b"</info>", "channel_count"),
        (TITTA.replace(b"<channel_count>37<", b"<channel_count>99999<"), "channel_count"),
        (TITTA.replace(b"<channel_count>37<", b"<channel_count>3<"), "describes 36 channels"),
    ):
        try:
            gaze_layout(parse_info(data))
        except MetadataError as exc:
            assert message in str(exc), (message, exc)
        else:
            raise AssertionError(f"{message}: accepted")
