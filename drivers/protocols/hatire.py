"""HATIRE binary head-tracker protocol (docs/protocols.md, HATIRE and Test vectors), free of I/O.

Every frame is 30 bytes, little-endian: 0xAAAA, a u16, 24 bytes, 0x5555. A data frame's u16 is the frame
counter Cpt (0..999, wrapping) and its 24 bytes are yaw, pitch, roll (float32 degrees) and three float32
accelerations. An info frame has a code >= 1000 instead (2000 version, 3001-3007 init, 5000 begin,
5001 start, 5002 stop, 5003 reset, 9xxx errors) and 24 bytes of NUL-padded text. The host sends single
characters: S start, s stop, R reset, C calibrate, V version, I info (answered in plain text lines).
HatireFramer takes byte chunks of any size, returns decoded frames, and discards (and counts) bytes
that are not part of a frame.

Angles: HATIRE gives no axes (docs/protocols.md, HATIRE); the firmware sends the MPU6050 DMP's yaw, pitch and roll,
which this module takes in the Razor convention (X forward, Y right, Z down, yaw -> pitch -> roll), so
drivers.protocols.razor.ypr_to_quat converts them to the head frame.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from drivers.protocols.framing import FrameFormatError, Framer

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


@dataclass(frozen=True)
class HatireFrame:
    """A data frame: counter, angles in degrees, accelerations as sent."""

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
