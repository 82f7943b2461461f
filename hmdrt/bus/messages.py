"""What travels on the bus and in native traces: gaze, pose and driver status messages.

Conventions (docs/architecture.md): times are integer nanoseconds; t_host on the host's monotonic clock (the
device's capture time mapped through the driver's clock-sync estimate), t_dev the device's own clock
as received, scaled to nanoseconds. Gaze directions are unit vectors in the head frame (right-handed,
+Y up, -Z forward) per eye (L, R) or combined (C), with optional vergence depth in metres. Pose is
the head position (m) and orientation quaternion (w, x, y, z). Invalid samples (blinks, lost
tracking) are kept with valid = false rather than dropped, so they can be counted and replayed.

On the bus a message is two frames: the topic (gaze.<device>, pose.<device>, status.<device>) and a
msgpack map of the message's fields plus the schema version v.
"""

from __future__ import annotations

import math
from typing import Annotated

import msgspec
import numpy as np

from hmdrt.ranges import Finite
from hmdrt.spatial import unit

SCHEMA_VERSION = 1
MAX_PAYLOAD_BYTES = 64 * 1024
MAX_TOPIC_BYTES = 256  # "status." and a device name; refused before the topic is decoded

Vec3 = tuple[Finite, Finite, Finite]
Quat = tuple[Finite, Finite, Finite, Finite]
TimeNs = Annotated[int, msgspec.Meta(ge=-(2**62), le=2**62)]
Count = Annotated[int, msgspec.Meta(ge=0)]


class _Message(msgspec.Struct, frozen=True, tag_field="kind", forbid_unknown_fields=True, omit_defaults=True):
    pass


class Gaze(_Message, tag="gaze"):
    seq: Count
    t_host: TimeNs
    t_dev: TimeNs | None = None
    valid: bool = True
    C: Vec3 | None = None
    L: Vec3 | None = None
    R: Vec3 | None = None
    depth_m: Annotated[float, msgspec.Meta(gt=0, le=1e6)] | None = None

    def eye_directions(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """Unit (left, right) gaze of a sample with at least one direction: each eye's own, else the combined
        one, else the other eye's."""
        left = next(v for v in (self.L, self.C, self.R) if v is not None)
        right = next(v for v in (self.R, self.C, self.L) if v is not None)
        return unit(left), unit(right)


class Pose(_Message, tag="pose"):
    seq: Count
    t_host: TimeNs
    position: Vec3
    orientation: Quat
    t_dev: TimeNs | None = None
    valid: bool = True


class ClockEstimate(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A driver's device-to-host clock map: t_host = t_dev + offset_ns + drift_ppm 1e-6 (t_dev - t_ref)."""

    offset_ns: float
    drift_ppm: float
    residual_ns: float  # RMS misfit of the lower envelope the estimate follows
    t_ref_ns: int = 0
    pairs: int = 0
    floor_ns: float = 0.0  # the latency floor taken out: known device latency, or measured by round-trip probes


class Status(_Message, tag="status"):
    """A driver's health, published about once a second."""

    device: str
    state: str  # connecting | connected | lost | crashed | closed
    t_host: TimeNs
    samples: Count = 0  # published samples (valid and invalid)
    invalid: Count = 0  # published with valid = false
    dropped: Count = 0  # lost before publishing: gaps in the device's sequence, queue overflow
    malformed: Count = 0  # device messages that did not parse
    reconnects: Count = 0
    clock: ClockEstimate | None = None
    detail: str = ""


Message = Gaze | Pose | Status


def numpy_scalar(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    raise NotImplementedError(f"cannot encode {type(obj).__name__}")


class MalformedMessage(ValueError):
    """A bus message that cannot be decoded or fails validation."""


def usable(sample: Gaze | Pose) -> bool:
    """Whether a sample can drive a frame: valid, with unit gaze directions or a unit quaternion."""
    if not sample.valid:
        return False
    unit = lambda v: v is not None and abs(math.hypot(*v) - 1.0) <= 1e-3  # noqa: E731
    if isinstance(sample, Pose):
        return unit(sample.orientation)
    eyes = [v for v in (sample.C, sample.L, sample.R) if v is not None]
    return bool(eyes) and all(unit(v) for v in eyes)


def topic(message: Message, device: str) -> bytes:
    return f"{'status' if isinstance(message, Status) else message.__struct_config__.tag}.{device}".encode()


def pack(topic: bytes, fields: dict) -> list[bytes]:
    """The two frames of a bus message: topic and msgpack payload of fields plus the schema version."""
    return [topic, msgspec.msgpack.encode({**fields, "v": SCHEMA_VERSION}, enc_hook=numpy_scalar)]


def encode(message: Message, device: str) -> list[bytes]:
    """A gaze, pose or status message of a device as bus frames."""
    return pack(topic(message, device), msgspec.to_builtins(message, enc_hook=numpy_scalar))


def decode(frames: list[bytes]) -> tuple[str, str, Message]:
    """(kind, device, message) of a two-frame bus message; MalformedMessage when anything is off."""
    if len(frames) != 2:
        raise MalformedMessage(f"expected 2 frames, got {len(frames)}")
    raw_topic, payload = frames
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise MalformedMessage(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    if len(raw_topic) > MAX_TOPIC_BYTES:
        raise MalformedMessage(f"topic of {len(raw_topic)} bytes exceeds {MAX_TOPIC_BYTES}")
    try:
        kind, _, device = raw_topic.decode("ascii").partition(".")
        fields = msgspec.msgpack.decode(payload)
        version = fields.pop("v", None) if isinstance(fields, dict) else None
        if type(version) is not int or version != SCHEMA_VERSION:  # True and 1.0 are not version 1
            raise MalformedMessage("missing or unknown schema version")
        message = msgspec.convert(fields, Message)
    except (UnicodeDecodeError, msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise MalformedMessage(str(exc)) from None
    except RecursionError:  # msgspec's guard against nesting deeper than the interpreter's recursion limit
        raise MalformedMessage("payload nested too deeply") from None
    expected = "status" if isinstance(message, Status) else message.__struct_config__.tag
    if kind != expected or not device:
        raise MalformedMessage(f"topic {raw_topic!r} does not match a {expected} message")
    return kind, device, message
