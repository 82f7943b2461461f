"""HATIRE binary head-tracker protocol (docs/protocols.md, HATIRE and Test vectors), free of I/O.

Every frame is 30 bytes, little-endian: 0xAAAA, a u16, 24 bytes, 0x5555. A data frame's u16 is the frame
counter Cpt (0..999, wrapping) and its 24 bytes are three float32 rotation fields (degrees) and three more float32
fields (HATino's gyro [Y, P, R] and acc [x, y, z]). An info frame has a code >= 1000 instead (2000 version,
3001-3007 init, 5000 begin, 5001 start, 5002 stop, 5003 reset, 9xxx errors) and 24 bytes of NUL-padded text.
The host sends single characters: S start, s stop, R reset, C calibrate, V version, I info (answered in plain
text lines). HatireFramer takes byte chunks of any size, returns decoded frames, and discards (and counts)
bytes that are not part of a frame.

Axes (docs/protocols.md, HATIRE): the protocol names no axes; a host maps fields to axes. AxisMapping is the mapping
of opentrack's tracker-hatire (which frame field feeds each of yaw, pitch, roll and x, y, z, and which are inverted),
its defaults opentrack's: yaw from rotation field 0, roll from 1, pitch from 2, each clamped to +-180 degrees,
translations off. The angles are opentrack's (yaw positive turning right, pitch nose up, roll positive raising the
right side, applied yaw -> pitch -> roll); opentrack_to_quat turns them into a head-frame orientation.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from hmdrt.drivers.protocols import razor
from hmdrt.drivers.protocols.framing import FrameFormatError, Framer

BAUD = 115200
RATE_HZ = 100.0
FRAME_SIZE = 30
BEGIN = b"\xaa\xaa"
END = b"\x55\x55"
COUNTER_WRAP = 1000

START, STOP, RESET, CALIBRATE, VERSION, INFO = b"S", b"s", b"R", b"C", b"V", b"I"
CODE_VERSION, CODE_BEGIN, CODE_START, CODE_STOP, CODE_RESET = 2000, 5000, 5001, 5002, 5003

_DATA = struct.Struct("<HH6fH")
_INFO = struct.Struct("<HH24sH")
_MARK_BEGIN, _MARK_END = 0xAAAA, 0x5555
MAX_ACCEL = 1e6


ROTATIONS = ("yaw", "pitch", "roll")
TRANSLATIONS = ("x", "y", "z")
AXES = ROTATIONS + TRANSLATIONS
OFF = "off"
CLAMP_DEG = 180.0  # opentrack clamps each rotation field to +-180 degrees before mapping


@dataclass(frozen=True)
class HatireFrame:
    """A data frame: counter, the three rotation fields (degrees) and the three trailing fields, under the names the
    firmware gives them (HATino: gyro [Y, P, R] and acc [x, y, z]); AxisMapping decides what they mean."""

    cpt: int
    yaw: float
    pitch: float
    roll: float
    acc: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class HatireInfo:
    code: int
    message: str


class HatireFormatError(FrameFormatError):
    """Bytes that are not a valid HATIRE frame."""


@dataclass(frozen=True)
class AxisMapping:
    """Which frame field (0, 1, 2; None: the axis is off and reads 0) feeds each opentrack axis, and which axes are
    negated: the axis settings of opentrack's tracker-hatire (TrackerSettings), with its defaults."""

    yaw: int | None = 0
    pitch: int | None = 2
    roll: int | None = 1
    x: int | None = None
    y: int | None = None
    z: int | None = None
    invert: frozenset[str] = frozenset()

    @classmethod
    def parse(cls, fields: Mapping[str, str], invert: str = "") -> AxisMapping:
        """A mapping from option text: fields maps an axis name to "0", "1", "2" or "off" (axes not given keep their
        default), invert is a comma-separated list of axis names; ValueError names the first bad value."""
        chosen: dict[str, int | None] = {}
        for axis, text in fields.items():
            if axis not in AXES:
                raise ValueError(f"no axis {axis!r}; axes: {', '.join(AXES)}")
            if text not in ("0", "1", "2", OFF):
                raise ValueError(f"{axis}_axis must be 0, 1, 2 or {OFF}, got {text!r}")
            chosen[axis] = None if text == OFF else int(text)
        names = [name for name in invert.split(",") if name]
        if unknown := [name for name in names if name not in AXES]:
            raise ValueError(f"invert takes a comma-separated list of {', '.join(AXES)}; got {unknown[0]!r}")
        return cls(**chosen, invert=frozenset(names))

    def angles(self, frame: HatireFrame) -> tuple[float, float, float]:
        """opentrack's (yaw, pitch, roll) in degrees of a data frame: rotation fields clamped to +-180, then mapped."""
        rotation = [min(max(v, -CLAMP_DEG), CLAMP_DEG) for v in (frame.yaw, frame.pitch, frame.roll)]
        yaw, pitch, roll = (self._value(axis, rotation) for axis in ROTATIONS)
        return yaw, pitch, roll

    def translation(self, frame: HatireFrame) -> tuple[float, float, float]:
        """opentrack's (x, y, z) of a data frame, as sent (opentrack takes centimetres): the trailing fields, mapped."""
        x, y, z = (self._value(axis, frame.acc) for axis in TRANSLATIONS)
        return x, y, z

    def rotation_fields(self, yaw: float, pitch: float, roll: float) -> tuple[float, float, float]:
        """The rotation fields a device sends for these opentrack angles under this mapping (what an emulated device
        writes); a field no axis reads is 0."""
        fields = [0.0, 0.0, 0.0]
        for axis, value in zip(ROTATIONS, (yaw, pitch, roll), strict=True):
            if (field := getattr(self, axis)) is not None:
                fields[field] = -value if axis in self.invert else value
        return fields[0], fields[1], fields[2]

    def _value(self, axis: str, values: Sequence[float]) -> float:
        field = getattr(self, axis)
        value = 0.0 if field is None else float(values[field])
        return -value if axis in self.invert else value


def opentrack_to_quat(yaw: float, pitch: float, roll: float) -> tuple[float, float, float, float]:
    """Head-frame orientation (w, x, y, z) of opentrack angles in degrees: Razor's convention with roll negated."""
    return razor.ypr_to_quat(yaw, pitch, -roll)


def quat_to_opentrack(q) -> tuple[float, float, float]:
    """opentrack's (yaw, pitch, roll) in degrees of a head-frame orientation (w, x, y, z); the inverse of
    opentrack_to_quat with pitch within +-90 degrees."""
    yaw, pitch, roll = razor.quat_to_ypr(q)
    return yaw, pitch, -roll


def opentrack_to_position(x_cm: float, y_cm: float, z_cm: float) -> tuple[float, float, float]:
    """Head-frame position in metres of opentrack's translation in centimetres (x positive left, y up, z back)."""
    return -x_cm / 100.0, y_cm / 100.0, z_cm / 100.0


def encode_frame(f: HatireFrame) -> bytes:
    if not 0 <= f.cpt < COUNTER_WRAP:
        raise HatireFormatError(f"frame counter must be within 0..999, got {f.cpt}")
    return _DATA.pack(_MARK_BEGIN, f.cpt, f.yaw, f.pitch, f.roll, *f.acc, _MARK_END)


def encode_info(code: int, message: str) -> bytes:
    """An info frame as the firmware sends it: message NUL-padded, its last byte a line feed."""
    text = message.encode("ascii")[:23]
    if not COUNTER_WRAP <= code <= 0xFFFF:
        raise HatireFormatError(f"info codes are 1000..65535, got {code}")
    return _INFO.pack(_MARK_BEGIN, code, text.ljust(23, b"\0") + b"\n", _MARK_END)


def decode_frame(data: bytes) -> HatireFrame | HatireInfo:
    """A 30-byte frame; HatireFormatError for wrong size, markers or values (non-finite, angle beyond 360)."""
    if len(data) != FRAME_SIZE or data[:2] != BEGIN or data[-2:] != END:
        raise HatireFormatError(f"not a {FRAME_SIZE}-byte frame between aa aa and 55 55: {bytes(data[:8]).hex(' ')}")
    code = int.from_bytes(data[2:4], "little")
    if code >= COUNTER_WRAP:
        text = _INFO.unpack(data)[2].rstrip(b"\n").split(b"\0", 1)[0]
        return HatireInfo(code, text.decode("ascii", errors="replace"))
    _, cpt, yaw, pitch, roll, ax, ay, az, _ = _DATA.unpack(data)
    if not all(math.isfinite(v) and abs(v) <= 360.0 for v in (yaw, pitch, roll)):
        raise HatireFormatError(f"angles not finite or beyond 360 degrees: {yaw}, {pitch}, {roll}")
    if not all(math.isfinite(v) and abs(v) <= MAX_ACCEL for v in (ax, ay, az)):
        raise HatireFormatError(f"accelerations not finite or beyond {MAX_ACCEL}: {ax}, {ay}, {az}")
    return HatireFrame(cpt, yaw, pitch, roll, (ax, ay, az))


class HatireFramer(Framer[HatireFrame | HatireInfo]):
    """Finds 30-byte frames between their aa aa and 55 55 markers."""

    _decode = staticmethod(decode_frame)

    def _next_size(self) -> int | None:
        while True:
            start = self._buf.find(BEGIN)
            if start < 0:
                self._drop(len(self._buf) - (self._buf[-1:] == BEGIN[:1]))  # keep a lone aa: a start may follow
                return None
            self._drop(start)
            if len(self._buf) < FRAME_SIZE:
                return None
            if self._buf[FRAME_SIZE - 2 : FRAME_SIZE] == END:
                return FRAME_SIZE
            self._drop(1)  # a false start: look for the next aa aa
