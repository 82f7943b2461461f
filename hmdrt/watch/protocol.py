"""What travels between the watch server and its page over the websocket (and POST /api/command).

The page sends commands as JSON objects of at most MAX_MESSAGE_BYTES: {"cmd": "set", "method": "rrm?fovea_deg=5"}
or {"cmd": "set", "params": {"fovea_deg": 5}}, {"cmd": "snapshot"} (optionally "path": a file name), {"cmd":
"shutdown"}, each with an optional numeric "id" that the reply repeats. Anything else is refused with BadMessage,
checked here before anything reaches the compositor, which checks the values again.

The server sends JSON text messages with a "type" (hello, frames, stats, status, log, reply) and each preview as
one binary message: a 4-byte big-endian header length, the JSON header (vsync, method, size, each eye's gaze point
and foveal radii in preview pixels), then the JPEG.
"""

from __future__ import annotations

import struct
from typing import Annotated

import msgspec

MAX_MESSAGE_BYTES = 4096
MAX_FRAMES_PER_BATCH = 256  # frame points per "frames" message; more arriving between flushes are counted, not sent

Name = Annotated[str, msgspec.Meta(min_length=1, max_length=64)]
Value = Annotated[str, msgspec.Meta(max_length=200)] | int | float | bool


class BadMessage(ValueError):
    """A page message that is not a command this server forwards; its text says why."""


class _Command(msgspec.Struct, frozen=True, forbid_unknown_fields=True, tag_field="cmd"):
    id: Annotated[int, msgspec.Meta(ge=0, le=2**53)] = 0


class Set(_Command, tag="set"):
    method: Annotated[str, msgspec.Meta(min_length=1, max_length=200)] | None = None
    params: Annotated[dict[Name, Value], msgspec.Meta(max_length=32)] | None = None


class Snapshot(_Command, tag="snapshot"):
    path: Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9_-][A-Za-z0-9._-]{0,63}\.png$")] | None = None


class Shutdown(_Command, tag="shutdown"):
    pass


Command = Set | Snapshot | Shutdown
_decoder = msgspec.json.Decoder(Command)


def parse_command(data: str | bytes) -> Command:
    """The command of one page message; BadMessage when it is too long, not JSON, or not a command."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise BadMessage(f"a message is at most {MAX_MESSAGE_BYTES} bytes")
    try:
        command = _decoder.decode(data)
    except (msgspec.DecodeError, RecursionError) as exc:  # ValidationError is a DecodeError
        raise BadMessage(f"not a command: {exc}") from None
    if isinstance(command, Set) and command.method is None and not command.params:
        raise BadMessage('set takes "method": "name?key=value" and/or "params": {key: value}')
    return command


def control_request(command: Command) -> dict:
    """The control socket's request for a command: its fields but the page's id, those not given left out."""
    fields = msgspec.structs.asdict(command)
    del fields["id"]
    return {"cmd": command.__struct_config__.tag, **{k: v for k, v in fields.items() if v is not None}}


def frame_point(record: dict) -> dict:
    """What the page plots of a `frame` record."""
    params = record.get("params")
    return {
        "vsync": record.get("vsync"),
        "t_ns": record.get("actual_present_ns"),
        "shown": record.get("shown"),
        "missed": record.get("missed"),
        "frame_ms": record.get("frame_ms") if record.get("shown") != "repeat" else None,
        "gaze_ms": record.get("gaze_to_photon_ms"),
        "pose_ms": record.get("pose_to_photon_ms"),
        "level": record.get("level"),
        "method": record.get("method"),
        "params": {k: v for k, v in params.items() if type(v) in (int, float)} if isinstance(params, dict) else {},
    }


def preview_message(fields: dict) -> bytes:
    """The binary websocket message of a `preview` telemetry message: header length, JSON header, JPEG."""
    jpeg = fields.get("jpeg")
    if not isinstance(jpeg, bytes):
        raise BadMessage("a preview without its JPEG")
    header = msgspec.json.encode({k: v for k, v in fields.items() if k not in ("jpeg", "v")})  # NaN as null
    return struct.pack(">I", len(header)) + header + jpeg
