"""Razor AHRS text protocol (docs/protocols.md, Razor), and (yaw, pitch, roll) <-> head-frame quaternions.

The firmware streams `#YPR=<yaw>,<pitch>,<roll>\\r\\n` in degrees with two decimals at 50 Hz and 57600
baud (`#YPRAG=` adds accel and gyro; its first three values are the same angles). Commands need no
newline and may be concatenated: `#o0`/`#o1` stream off/on, `#ot` text, `#f` one frame, `#s<xy>`
answers `#SYNCH<xy>\\r\\n`; errors arrive as `!ERR: ...` lines. RazorFramer takes byte chunks of any
size, returns complete decoded lines, and discards (and counts) bytes that are not part of one.

Angles (section 5.1): body axes X forward, Y right, Z down; yaw positive clockwise seen from above
(turning right), pitch positive nose-up, roll positive right-side-down, applied yaw -> pitch -> roll
(intrinsic Z-Y-X, the aerospace convention). ypr_to_quat maps them to our head frame (+X right,
+Y up, -Z forward): device forward/right/down are head -Z/+X/-Y, so a device quaternion
(w, x, y, z) becomes (w, y, -z, -x). quat_to_ypr is its inverse (pitch within +-90 degrees).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from hmdrt.drivers.protocols.framing import FrameFormatError, Framer

BAUD = 57600
RATE_HZ = 50.0
START = b"#ot#o1#s00"  # text output, streaming on, and a sync token (#SYNCH00) that shows the firmware listens
MAX_LINE = 128  # longer than any frame the firmware sends (#YPRAG= with nine values)

_NUMBER = rb"-?\d{1,6}(?:\.\d{1,6})?"
_YPR = re.compile(rb"#YPR=(%s),(%s),(%s)" % (_NUMBER, _NUMBER, _NUMBER))
_YPRAG = re.compile(rb"#YPRAG=(%s),(%s),(%s)(?:,%s){6}" % ((_NUMBER,) * 4))
_SYNCH = re.compile(rb"#SYNCH([\x21-\x7e]{0,16})")
_ERROR = re.compile(rb"!ERR: ([\x20-\x7e]{0,100})")
_FRAME_START = re.compile(rb"[#!]")
_COMMAND = re.compile(rb"#(o[01tbcnx]|oe[01]|os[crb][tb]|f|s[\x21-\x7e]{2})")
_LONGEST_COMMAND = 5


@dataclass(frozen=True)
class Ypr:
    """Orientation in degrees, Razor convention."""

    yaw: float
    pitch: float
    roll: float


@dataclass(frozen=True)
class Synch:
    token: str


@dataclass(frozen=True)
class ErrorLine:
    text: str


RazorFrame = Ypr | Synch | ErrorLine


def check_angles(yaw: float, pitch: float, roll: float) -> None:
    """Raise ValueError unless yaw and roll lie within +-180 and pitch within +-90 degrees."""
    if not (abs(yaw) <= 180.0 and abs(pitch) <= 90.0 and abs(roll) <= 180.0):
        raise ValueError(f"angles out of range: yaw {yaw}, pitch {pitch}, roll {roll}")


class RazorFormatError(FrameFormatError):
    """A line that is not a Razor AHRS frame."""


def decode_line(line: bytes) -> RazorFrame:
    """One complete line (with its line end) as a frame; RazorFormatError when it is none."""
    body = line.rstrip(b"\r\n")
    if len(line) > MAX_LINE or not line.endswith(b"\n"):
        raise RazorFormatError(f"not a complete line of at most {MAX_LINE} bytes: {line[:40]!r}")
    if m := _YPR.fullmatch(body) or _YPRAG.fullmatch(body):
        ypr = Ypr(*(float(v) for v in m.groups()))
        try:
            check_angles(ypr.yaw, ypr.pitch, ypr.roll)
        except ValueError as exc:
            raise RazorFormatError(str(exc)) from None
        return ypr
    if m := _SYNCH.fullmatch(body):
        return Synch(m.group(1).decode("ascii"))
    if m := _ERROR.fullmatch(body):
        return ErrorLine(m.group(1).decode("ascii"))
    raise RazorFormatError(f"not a Razor frame: {body[:40]!r}")


def encode_ypr(yaw: float, pitch: float, roll: float) -> bytes:
    """The text frame the firmware sends (two decimals)."""
    check_angles(yaw, pitch, roll)
    return b"#YPR=%.2f,%.2f,%.2f\r\n" % (yaw, pitch, roll)


def encode_synch(token: str) -> bytes:
    return b"#SYNCH" + token.encode("ascii") + b"\r\n"


class RazorFramer(Framer[RazorFrame]):
    """Finds lines that start at # or ! and end at a line feed; a new start cuts an unfinished line."""

    _decode = staticmethod(decode_line)

    def _next_size(self) -> int | None:
        while self._buf:
            start = _FRAME_START.search(self._buf)
            if start is None:
                self._drop(len(self._buf))
                return None
            self._drop(start.start())
            end = self._buf.find(b"\n")
            following = _FRAME_START.search(self._buf, 1)
            if following is not None and (end < 0 or following.start() < end):
                self._drop(following.start())  # a frame start before this line ended: the line was cut
                continue
            if end < 0:
                if len(self._buf) > MAX_LINE:
                    self._drop(len(self._buf))
                return None
            return end + 1
        return None


def parse_commands(data: bytes) -> tuple[list[str], bytes]:
    """Commands in bytes the host wrote (e.g. b"#ob#o1#s12" -> ["ob", "o1", "s12"]) and an unfinished tail."""
    commands: list[str] = []
    pos = 0
    while (pos := data.find(b"#", pos)) >= 0:
        m = _COMMAND.match(data, pos)
        if m:
            commands.append(m.group(1).decode("ascii"))
            pos = m.end()
        elif len(data) - pos < _LONGEST_COMMAND:
            return commands, data[pos:]
        else:
            pos += 1
    return commands, b""


def ypr_to_quat(yaw_deg: float, pitch_deg: float, roll_deg: float) -> tuple[float, float, float, float]:
    """Head-frame orientation (w, x, y, z) of Razor-convention angles in degrees."""
    cy, sy = math.cos(math.radians(yaw_deg) / 2), math.sin(math.radians(yaw_deg) / 2)
    cp, sp = math.cos(math.radians(pitch_deg) / 2), math.sin(math.radians(pitch_deg) / 2)
    cr, sr = math.cos(math.radians(roll_deg) / 2), math.sin(math.radians(roll_deg) / 2)
    w = cr * cp * cy + sr * sp * sy
    x = sr * cp * cy - cr * sp * sy  # device axes: x forward, y right, z down
    y = cr * sp * cy + sr * cp * sy
    z = cr * cp * sy - sr * sp * cy
    return w, y, -z, -x


def quat_to_ypr(q) -> tuple[float, float, float]:
    """Razor-convention (yaw, pitch, roll) in degrees of a head-frame orientation (w, x, y, z)."""
    w, hx, hy, hz = (float(c) for c in q)
    x, y, z = -hz, hx, -hy
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return math.degrees(yaw), math.degrees(pitch), math.degrees(roll)
