"""XDF Gaze meta-data of an LSL stream, and its samples as gaze in the head frame: free of I/O (docs/protocols.md, LSL).

The meta-data (sccn/xdf wiki, Gaze-Meta-Data): the stream info's <desc><channels> holds a <channel> per channel with
its label, eye (left, right or both), type and unit. Read here: DirectionX/Y/Z (a 3D gaze vector),
IntersectionX/Y/Z (the 3D gaze point) with PupilX/Y/Z or PositionX/Y/Z (where the eye is: the ray's origin),
ScreenX/Y (the gaze on a screen, in pixels or normalized) and Confidence, and TittaLSL's ValidFlag, which says
whether the values of its eye listed since the eye's previous flag are valid (dcnieho/Titta,
LSL_streamer/src/TittaLSL.cpp @ 0610aaf). An eye's gaze comes from the first of Direction, Intersection less the
origin, and Screen that has values in that sample; of several channels of one type and eye the first is read (the
Pupil Capture relay types its eye centres and then its gaze normals PositionX/Y/Z: labstreaminglayer/App-PupilLabs,
pupil_capture/pupil_capture_lsl_relay/channel.py @ 37dedd6). A channel without an eye is taken for both eyes, and
`metatype` is read where `type` is missing, as Pupil Labs' Neon relay writes it (pupil-labs/lsl-relay,
src/pupil_labs/lsl_relay/channels.py @ da699cf). Pupil sizes, eye positions and frame numbers are not carried: the
bus's gaze has no field for them.

3D vectors are in the publisher's axes, which the meta-data does not name: `axes` says which (head: x right, y up, z
backwards, hmdrt's head frame and Tobii's user coordinate system; opencv: y down and z forward, Pupil Core's world
camera; unity: y up and z forward, left-handed). Screen positions go through the eye cameras of an HMD profile, the
origin at the top left (Tobii's display area, screen pixels) or the bottom left (Pupil's norm_pos). In a sample NaN
is a missing value (Tobii's lost eye, the Pupil relay's other eye); an infinite value or one beyond MAX_VALUE makes
the sample malformed.
"""

from __future__ import annotations

import re
import xml.etree.ElementTree as ElementTree
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from hmdrt.drivers.base import DriverError
from hmdrt.optics import EyeCamera, HmdProfile
from hmdrt.spatial import Pose, mean_direction

MAX_XML_BYTES = 512 * 1024  # a gaze stream's info is a few KB (TittaLSL's 37 channels: about 9 KB)
MAX_CHANNELS = 1024
MAX_TEXT = 64  # characters kept of a label, eye, type or unit
MAX_LISTED = 40  # channels named in an error
MAX_VALUE = 1e9  # larger magnitudes are no gaze value: mm, pixels or a normalized position
MAX_DEPTH_M = 1e6  # the bus's vergence depth range (hmdrt.bus.messages.Gaze.depth_m)
EYES = ("left", "right", "both")
AXES = {"head": (1.0, 1.0, 1.0), "opencv": (1.0, -1.0, -1.0), "unity": (1.0, 1.0, -1.0)}
ORIGINS = ("top-left", "bottom-left")
METRES = {
    **dict.fromkeys(("mm", "millimeter", "millimeters", "millimetre", "millimetres"), 1e-3),
    **dict.fromkeys(("cm", "centimeter", "centimeters", "centimetre", "centimetres"), 1e-2),
    **dict.fromkeys(("m", "meter", "meters", "metre", "metres"), 1.0),
}
NORMALIZED = ("normalized", "normalised", "norm")
PIXELS = ("pixels", "pixel", "px")
NUMBERS = ("float32", "double64", "int8", "int16", "int32", "int64")
NEEDS = (
    "per eye (left, right or both) DirectionX/Y/Z, IntersectionX/Y/Z with PupilX/Y/Z or PositionX/Y/Z, or ScreenX/Y "
    "in pixels or normalized, each channel with label, eye, type and unit (XDF Gaze meta-data)"
)
_DECLARATION = re.compile(rb"<!\s*(doctype|entity)", re.IGNORECASE)


class MetadataError(DriverError):
    """A stream's meta-data is not XML hmdrt reads, or does not say where the gaze is; the message names the
    channels it describes."""


@dataclass(frozen=True)
class Channel:
    """One <channel> of the meta-data: its column, label, eye (lower case; "both" when not given), type, unit."""

    index: int
    label: str
    eye: str
    kind: str
    unit: str

    def describe(self) -> str:
        return f"{self.label or '#' + str(self.index)} [{self.kind or 'no type'}, {self.eye}, {self.unit or 'no unit'}]"


@dataclass(frozen=True)
class StreamMeta:
    """The parts of an LSL stream info (<info>) the driver reads."""

    name: str
    type: str
    source_id: str
    channel_count: int
    channel_format: str
    nominal_srate: float
    channels: tuple[Channel, ...]

    def title(self) -> str:
        return f"LSL stream {self.name!r} (type {self.type!r}, source_id {self.source_id!r})"

    def listing(self) -> str:
        """The described channels, for errors: up to MAX_LISTED of them and how many more."""
        if not self.channels:
            return "no channel described"
        named = "; ".join(c.describe() for c in self.channels[:MAX_LISTED])
        more = len(self.channels) - MAX_LISTED
        return f"channels {named}" + (f"; and {more} more" if more > 0 else "")


def _text(element: ElementTree.Element | None, tag: str) -> str:
    child = element.find(tag) if element is not None else None
    text = (child.text or "") if child is not None else ""
    return "".join(c for c in text.strip()[:MAX_TEXT] if c.isprintable())


def parse_info(xml: str | bytes) -> StreamMeta:
    """The stream info XML (StreamInfo.as_xml()) as a StreamMeta; MetadataError when it is too large, not XML,
    declares a DTD or entities, or has no channel count within 1-MAX_CHANNELS."""
    data = xml.encode("utf-8", "replace") if isinstance(xml, str) else bytes(xml)
    if len(data) > MAX_XML_BYTES:
        raise MetadataError(f"LSL stream info of {len(data)} bytes exceeds {MAX_XML_BYTES}")
    if _DECLARATION.search(data):
        raise MetadataError("LSL stream info declares a DTD or entities, which hmdrt does not read")
    try:
        root = ElementTree.fromstring(data)
    except ElementTree.ParseError as exc:
        raise MetadataError(f"LSL stream info is not XML: {exc}") from None
    count, rate = _text(root, "channel_count"), _text(root, "nominal_srate")
    if not (count.isdigit() and 1 <= int(count) <= MAX_CHANNELS):
        raise MetadataError(f"LSL stream info gives channel_count {count!r}, not a number within 1-{MAX_CHANNELS}")
    try:
        srate = float(rate) if rate else 0.0
    except ValueError:
        srate = 0.0
    channels = root.find("desc/channels")
    found = channels.findall("channel") if channels is not None else []
    if len(found) > int(count):
        raise MetadataError(f"LSL stream info describes {len(found)} channels of a stream of {count}")
    return StreamMeta(
        name=_text(root, "name"),
        type=_text(root, "type"),
        source_id=_text(root, "source_id"),
        channel_count=int(count),
        channel_format=_text(root, "channel_format"),
        nominal_srate=srate if 0.0 <= srate <= 1e6 else 0.0,  # 0: irregular, as LSL's IRREGULAR_RATE
        channels=tuple(
            Channel(
                index=i,
                label=_text(c, "label"),
                eye=_text(c, "eye").casefold() or "both",
                kind=_text(c, "type") or _text(c, "metatype"),
                unit=_text(c, "unit"),
            )
            for i, c in enumerate(found)
        ),
    )


@dataclass(frozen=True)
class Source:
    """Where one eye's gaze is: Direction (3 columns), Intersection (the point's 3, then the origin's 3) or Screen
    (2), with the metres per unit of each column (1 where it is no length)."""

    eye: str
    kind: str
    columns: tuple[int, ...]
    scales: tuple[float, ...]
    length: bool  # the vector's length is a distance: the gaze depth
    pixels: bool = False  # Screen in pixels, else normalized

    def describe(self, meta: StreamMeta) -> str:
        return f"{self.eye} eye from {'/'.join(meta.channels[i].kind for i in self.columns)}"


@dataclass(frozen=True)
class GazeLayout:
    """How a stream's columns make gaze: each eye's sources in the order they are tried, the eyes' Confidence
    columns, and the ValidFlag column that vouches for each value column."""

    meta: StreamMeta
    sources: tuple[Source, ...]
    confidence: dict[str, int]
    flags: dict[int, int]

    @property
    def used(self) -> list[int]:
        """Every column decoding reads."""
        columns = {c for s in self.sources for c in s.columns} | set(self.confidence.values())
        return sorted(columns | {self.flags[c] for c in columns if c in self.flags})

    def describe(self) -> str:
        return "; ".join(s.describe(self.meta) for s in self.sources)


def _unit(group: list[Channel], meta: StreamMeta) -> str:
    units = {c.unit.casefold() for c in group}
    if len(units) != 1:
        raise MetadataError(f"{meta.title()}: {', '.join(c.describe() for c in group)} must share one unit")
    return units.pop()


def _metres(group: list[Channel], meta: StreamMeta, required: bool) -> float | None:
    """Metres per unit of a group of channels; None (or a MetadataError, when required) if their unit is no length."""
    unit = _unit(group, meta)
    if unit not in METRES and required:
        raise MetadataError(
            f"{meta.title()}: {', '.join(c.describe() for c in group)} need a length unit ({', '.join(METRES)})"
        )
    return METRES.get(unit)


def gaze_layout(meta: StreamMeta) -> GazeLayout:
    """The gaze sources of a stream's meta-data; MetadataError, naming the channels described, when it has none or
    a channel is not one hmdrt can read (a string stream, an eye other than left, right or both, a unit that does
    not fit its type)."""
    if meta.channel_format.casefold() not in NUMBERS:
        raise MetadataError(f"{meta.title()} has channel format {meta.channel_format!r}; gaze needs numbers")
    for channel in meta.channels:
        if channel.eye not in EYES:
            raise MetadataError(f"{meta.title()}: channel {channel.describe()} has an eye other than {EYES}")
    first: dict[tuple[str, str], Channel] = {}
    for channel in meta.channels:
        first.setdefault((channel.eye, channel.kind.casefold()), channel)

    def group(eye: str, kind: str, axes: str = "xyz") -> list[Channel] | None:
        found = [first.get((eye, kind + axis)) for axis in axes]
        return found if all(found) else None

    sources = []
    for eye in EYES:
        origin = group(eye, "pupil") or group(eye, "position")
        if direction := group(eye, "direction"):
            metres = _metres(direction, meta, required=False)
            columns = tuple(c.index for c in direction)
            sources.append(Source(eye, "Direction", columns, (metres or 1.0,) * 3, length=metres is not None))
        if (point := group(eye, "intersection")) and origin:
            scales = (_metres(point, meta, required=True),) * 3 + (_metres(origin, meta, required=True),) * 3
            sources.append(Source(eye, "Intersection", tuple(c.index for c in point + origin), scales, length=True))
        if screen := group(eye, "screen", "xy"):
            unit = _unit(screen, meta)
            if unit not in NORMALIZED + PIXELS:
                raise MetadataError(
                    f"{meta.title()}: {', '.join(c.describe() for c in screen)} need unit pixels or normalized"
                )
            columns = tuple(c.index for c in screen)
            sources.append(Source(eye, "Screen", columns, (1.0, 1.0), length=False, pixels=unit in PIXELS))
    if not sources:
        raise MetadataError(f"{meta.title()} has no gaze hmdrt can read: {meta.listing()}; it needs {NEEDS}")
    confidence = {eye: first[(eye, "confidence")].index for eye in EYES if (eye, "confidence") in first}
    flags: dict[int, int] = {}
    pending: dict[str, list[int]] = {eye: [] for eye in EYES}
    for channel in meta.channels:
        kind = channel.kind.casefold()
        if kind == "validflag":
            flags.update(dict.fromkeys(pending[channel.eye], channel.index))
            pending[channel.eye] = []
        elif kind != "availableflag":
            pending[channel.eye].append(channel.index)
    return GazeLayout(meta, tuple(sources), confidence, flags)


class GazeRow(NamedTuple):
    """One sample's gaze: unit directions in the head frame (None: the eye has none) and the depth in metres."""

    valid: bool
    C: tuple[float, float, float] | None
    L: tuple[float, float, float] | None
    R: tuple[float, float, float] | None
    depth_m: float | None


def _row(directions: np.ndarray | None, i: int) -> tuple[float, float, float] | None:
    if directions is None or not np.isfinite(directions[i, 0]):
        return None
    x, y, z = (float(v) for v in directions[i])
    return x, y, z


class GazeDecoder:
    """Samples (rows of a stream's channels) as GazeRows, through a layout, the publisher's axes, an HMD profile's
    eye cameras for Screen positions, and a minimum confidence."""

    def __init__(
        self,
        layout: GazeLayout,
        axes: str = "head",
        profile: HmdProfile | None = None,
        origin: str = "top-left",
        min_confidence: float = 0.6,
    ):
        if axes not in AXES or origin not in ORIGINS:
            raise ValueError(f"axes must be one of {tuple(AXES)} and origin one of {ORIGINS}")
        self.layout = layout
        self.min_confidence = min_confidence
        self._signs = np.array(AXES[axes])
        self._bottom_up = origin == "bottom-left"
        self._cameras: dict[str, EyeCamera] = {}
        if any(s.kind == "Screen" for s in layout.sources):
            if profile is None:
                raise ValueError("Screen positions need an HMD profile")
            self._cameras = {eye: EyeCamera.for_eye(profile, Pose(), eye) for eye in ("left", "right")}

    def _screen(self, source: Source, xy: np.ndarray) -> np.ndarray:
        """Head-frame directions through pixel or normalized screen positions; both eyes' mean for eye "both"."""
        camera = next(iter(self._cameras.values()))
        size = np.array([camera.width, camera.height], dtype=np.float64)
        pixels = xy if source.pixels else xy * size
        if self._bottom_up:
            pixels = np.stack([pixels[:, 0], size[1] - pixels[:, 1]], axis=1)
        eyes = ("left", "right") if source.eye == "both" else (source.eye,)
        return sum(self._cameras[eye].directions(pixels).astype(np.float64) for eye in eyes)

    def _directions(self, source: Source, values: np.ndarray, ok: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Unit directions (NaN where not ok or degenerate) and vector lengths of one source's rows."""
        v = values[:, list(source.columns)] * np.array(source.scales)
        vectors = np.full((len(values), 3), np.nan)
        if source.kind == "Screen":
            vectors[ok] = self._screen(source, v[ok])
        elif source.kind == "Intersection":
            vectors[ok] = (v[ok, :3] - v[ok, 3:]) * self._signs
        else:
            vectors[ok] = v[ok] * self._signs
        length = np.linalg.norm(vectors, axis=1)
        good = ok & np.isfinite(length) & (length > 1e-12)
        units = np.full_like(vectors, np.nan)
        units[good] = vectors[good] / length[good, None]
        return units, np.where(good, length, np.nan)

    def _ok(self, source: Source, values: np.ndarray) -> np.ndarray:
        """Rows where a source's values are all there, vouched for by their flags, at the eye's confidence."""
        ok = np.isfinite(values[:, list(source.columns)]).all(axis=1)
        for column in source.columns:
            if column in self.layout.flags:
                ok &= np.nan_to_num(values[:, self.layout.flags[column]]) != 0.0
        for eye in {source.eye, "both"}:
            if eye in self.layout.confidence:
                ok &= np.nan_to_num(values[:, self.layout.confidence[eye]], nan=-1.0) >= self.min_confidence
        return ok

    def _eye(self, sources: list[Source], values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """One eye's unit directions and distances (m; NaN where none), each row from the first source that has it."""
        units, distance = np.full((len(values), 3), np.nan), np.full(len(values), np.nan)
        for source in sources:
            todo = ~np.isfinite(units[:, 0])
            found, length = self._directions(source, values, self._ok(source, values) & todo)
            took = np.isfinite(found[:, 0])
            units[took] = found[took]
            if source.length:
                distance[took] = length[took]  # in metres: the columns were scaled
        return units, distance

    def decode(self, rows: np.ndarray) -> list[GazeRow | None]:
        """Each row (n, channel_count) as a GazeRow, or None when it is malformed."""
        values = np.asarray(rows, dtype=np.float64).reshape(-1, self.layout.meta.channel_count)
        with np.errstate(invalid="ignore", over="ignore"):
            malformed = (np.abs(values[:, self.layout.used]) > MAX_VALUE).any(axis=1)
            directions: dict[str, np.ndarray] = {}
            depths = []
            for eye in EYES:
                sources = [s for s in self.layout.sources if s.eye == eye]
                if sources:
                    directions[eye], distance = self._eye(sources, values)
                    depths.append((eye, distance))
        depth = _depth(depths, len(values))
        out: list[GazeRow | None] = []
        for i in range(len(values)):
            if malformed[i]:
                out.append(None)
                continue
            left, right = _row(directions.get("left"), i), _row(directions.get("right"), i)
            centre = _row(directions.get("both"), i)
            if centre is None and left is not None and right is not None:
                centre = mean_direction(left, right)
            valid = any(v is not None for v in (left, right, centre))
            d = float(depth[i])
            out.append(GazeRow(valid, centre, left, right, d if valid and 0.0 < d <= MAX_DEPTH_M else None))
        return out


def _depth(depths: list[tuple[str, np.ndarray]], n: int) -> np.ndarray:
    """Per row: the both-eyes source's distance, else the mean of the eyes' (NaN where none)."""
    by_eye = dict(depths)
    if "both" in by_eye:
        both = by_eye.pop("both")
    else:
        both = np.full(n, np.nan)
    if by_eye:
        stacked = np.stack(list(by_eye.values()))
        counts = np.isfinite(stacked).sum(axis=0)
        means = np.where(counts > 0, np.nansum(stacked, axis=0) / np.maximum(counts, 1), np.nan)
        both = np.where(np.isfinite(both), both, means)
    return both
