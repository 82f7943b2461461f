"""FOVE eye-tracker data over TCP: the records and their framing (the wire spec of fove:// and the emulator).

FOVE has no public wire protocol; its client library talks to FoveService over local IPC
(docs/protocols.md, FOVE). hmdrt serves the FOVE API data model (section 2) over this small framing:

Framing. Each frame is a big-endian u32 payload length N followed by N bytes: one msgpack map, with
N at most 65536 (MAX_FRAME_BYTES). A larger N cannot be skipped safely, so the reader raises
FrameTooLarge and the connection is closed; a payload that does not decode or validate is a
FrameError and the stream goes on with the next frame.

Records. Every map has "type"; unknown keys are refused; numbers must be finite (|v| <= 1e6), and
unit length is the reader's check. Vectors are [x, y, z] floats in FOVE's head frame: LEFT-handed,
+X right, +Y up, +Z forward, metres (section 2; section 10 notes the handedness is inferred).
Timestamps are u64 microseconds on the device's clock (unspecified epoch); ids are u64 frame
counters that increase by one per frame, so a gap is a lost frame (section 2: "use the frame id").

    hello      server -> client, once on connect: api_version str, capabilities u32 (bit n is
               Capability n of section 2, v1.x), eye_rate_hz (120), display_rate_hz (70)
    subscribe  client -> server: the capabilities it wants; only offered ones are served.
               EyeTracking -> "eye" records; Orientation or Position -> "pose" records
    eye        id, timestamp, gaze_left, gaze_right (unit vectors), state_left, state_right
               (EyeState: NotDetected 0, Opened 1, Closed 2), ray_origin and ray_direction (the
               combined gaze ray, origin between the eyes), depth (combined gaze depth in metres, or
               nil when unknown), result (0 ok, 1003 Data_NoUpdate, 1006 Data_Unreliable,
               1007 Data_LowAccuracy). On lost tracking the gaze vectors are (0, 0, 1) (section 2).
    pose       id, timestamp, orientation [x, y, z, w] (FOVE's order, unit), position (metres, tared)

Coordinates. FOVE's frame is ours (docs/architecture.md, Conventions: right-handed, -Z forward) mirrored in z, so one
reflection converts either way (mirror_vector, mirror_quaternion; each is its own inverse).
"""

from __future__ import annotations

import enum
import struct
from typing import Annotated, Literal

import msgspec

MAX_FRAME_BYTES = 64 * 1024
API_VERSION = "1.0"
EYE_RATE_HZ = 120.0
DISPLAY_RATE_HZ = 70.0

_LENGTH = struct.Struct(">I")


class Capability(enum.IntFlag):
    """ClientCapabilities of the FOVE v1.x API (docs/protocols.md, FOVE): bit n."""

    ORIENTATION = 1 << 0
    POSITION = 1 << 1
    POSITION_IMAGE = 1 << 2
    EYE_TRACKING = 1 << 3
    GAZE_DEPTH = 1 << 4
    USER_PRESENCE = 1 << 5
    USER_ATTENTION_SHIFT = 1 << 6
    USER_IOD = 1 << 7
    USER_IPD = 1 << 8
    EYE_TORSION = 1 << 9
    EYE_SHAPE = 1 << 10
    EYES_IMAGE = 1 << 11
    EYEBALL_RADIUS = 1 << 12
    IRIS_RADIUS = 1 << 13
    PUPIL_RADIUS = 1 << 14
    GAZED_OBJECT_DETECTION = 1 << 15
    DIRECT_SCREEN_ACCESS = 1 << 16
    PUPIL_SHAPE = 1 << 17
    EYE_BLINK = 1 << 18


class EyeState(enum.IntEnum):
    NOT_DETECTED = 0
    OPENED = 1
    CLOSED = 2


class Result(enum.IntEnum):
    """The ErrorCode values an eye frame can carry (section 2)."""

    OK = 0
    DATA_NO_UPDATE = 1003
    DATA_UNRELIABLE = 1006
    DATA_LOW_ACCURACY = 1007


LOST_GAZE = (0.0, 0.0, 1.0)  # FOVE's gaze vector when tracking is lost

Component = Annotated[float, msgspec.Meta(ge=-1e6, le=1e6)]  # of a vector or quaternion FOVE sends: finite
Vec3 = tuple[Component, Component, Component]
Quat = tuple[Component, Component, Component, Component]
U64 = Annotated[int, msgspec.Meta(ge=0)]
Caps = Annotated[int, msgspec.Meta(ge=0, lt=2**32)]
Rate = Annotated[float, msgspec.Meta(gt=0, le=10_000)]
StateCode = Literal[0, 1, 2]
ResultCode = Literal[0, 1003, 1006, 1007]


class _Record(msgspec.Struct, frozen=True, tag_field="type", forbid_unknown_fields=True):
    pass


class Hello(_Record, tag="hello"):
    api_version: str
    capabilities: Caps
    eye_rate_hz: Rate = EYE_RATE_HZ
    display_rate_hz: Rate = DISPLAY_RATE_HZ


class Subscribe(_Record, tag="subscribe"):
    capabilities: Caps


class Eye(_Record, tag="eye"):
    id: U64
    timestamp: U64
    gaze_left: Vec3
    gaze_right: Vec3
    state_left: StateCode
    state_right: StateCode
    ray_origin: Vec3
    ray_direction: Vec3
    depth: Annotated[float, msgspec.Meta(ge=0, le=1e6)] | None
    result: ResultCode


class Pose(_Record, tag="pose"):
    id: U64
    timestamp: U64
    orientation: Quat  # x, y, z, w
    position: Vec3


Record = Hello | Subscribe | Eye | Pose

_decoder = msgspec.msgpack.Decoder(Record)
_encoder = msgspec.msgpack.Encoder()


class FrameError(ValueError):
    """A frame whose payload is not a valid record; the stream continues with the next frame."""


class FrameTooLarge(FrameError):
    """A frame header announcing more than MAX_FRAME_BYTES; the stream cannot be resynchronised."""


def encode(record: Record) -> bytes:
    """One frame: length prefix and msgpack payload."""
    payload = _encoder.encode(record)
    return _LENGTH.pack(len(payload)) + payload


def decode(payload: bytes) -> Record:
    """The record in one frame's payload; FrameError when it does not decode or validate."""
    try:
        return _decoder.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise FrameError(str(exc)) from None
    except RecursionError:  # values skipped while looking for "type", nested deeper than msgspec follows
        raise FrameError("payload nested too deeply") from None


class FrameReader:
    """Splits a byte stream into frame payloads, holding at most one frame's worth of bytes."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def feed(self, data: bytes) -> list[bytes]:
        """Payloads of the frames completed by `data`; FrameTooLarge on an oversize header."""
        self._buffer += data
        payloads = []
        while len(self._buffer) >= _LENGTH.size:
            (size,) = _LENGTH.unpack_from(self._buffer)
            if size > MAX_FRAME_BYTES:
                raise FrameTooLarge(f"frame of {size} bytes exceeds {MAX_FRAME_BYTES}")
            end = _LENGTH.size + size
            if len(self._buffer) < end:
                break
            payloads.append(bytes(self._buffer[_LENGTH.size : end]))
            del self._buffer[:end]
        return payloads


def mirror_vector(v) -> tuple[float, float, float]:
    """A direction or position between FOVE's frame and ours: (x, y, z) -> (x, y, -z)."""
    x, y, z = (float(c) for c in v)
    return (x, y, -z)


def mirror_quaternion(q_wxyz) -> tuple[float, float, float, float]:
    """An orientation between FOVE's frame and ours: (w, x, y, z) -> (w, -x, -y, z).

    With S = diag(1, 1, -1) the rotation in the other frame is S R S; conjugating by a reflection keeps
    the angle and maps the axis a to -S a, which negates x and y of the quaternion's vector part.
    """
    w, x, y, z = (float(c) for c in q_wxyz)
    return (w, -x, -y, z)


def from_fove_quaternion(q_xyzw) -> tuple[float, float, float, float]:
    """FOVE's wire orientation (x, y, z, w) as our (w, x, y, z)."""
    x, y, z, w = q_xyzw
    return mirror_quaternion((w, x, y, z))


def to_fove_quaternion(q_wxyz) -> tuple[float, float, float, float]:
    """Our orientation (w, x, y, z) as FOVE's wire (x, y, z, w)."""
    w, x, y, z = mirror_quaternion(q_wxyz)
    return (x, y, z, w)
