"""What travels between the watch server and its page over the websocket (and POST /api/command).

The page sends a control command (hmdrt.compositor.commands declares them) as a JSON object of at most
MAX_MESSAGE_BYTES, with an optional numeric "id" that the reply repeats: {"cmd": "set", "method": "rrm?fovea_deg=5"},
{"cmd": "set", "params": {"fovea_deg": 5}}, {"cmd": "snapshot"}, {"cmd": "shutdown"}. It is checked here by the
same declaration the control socket checks it by, so a bad one is refused with the control socket's message
before anything reaches the compositor.

The server sends JSON text messages with a "type" (hello, frames, stats, status, log, reply) and each preview as
one binary message: a 4-byte big-endian header length, the JSON header (vsync, method, size, each eye's gaze point
and foveal radii in preview pixels), then the JPEG.
"""

from __future__ import annotations

import struct
from typing import NamedTuple

import msgspec

from hmdrt.compositor import commands

MAX_MESSAGE_BYTES = 4096
MAX_FRAMES_PER_BATCH = 256  # frame points per "frames" message; more arriving between flushes are counted, not sent
MAX_ID = 2**53  # a page's message id: any integer JavaScript holds exactly
GAZE_ERROR_KEYS = ("vsync", "left_deg", "right_deg", "fovea_deg")  # of each of a record's gaze_errors
MAX_GAZE_ERRORS = 32  # of a record's gaze_errors passed on (the compositor puts at most 32 into one)


class BadMessage(ValueError):
    """A page message that is not a command this server forwards; its text says why."""


class PageCommand(NamedTuple):
    """A command from a page and the id its reply repeats."""

    id: int
    command: commands.Command


def parse_command(data: str | bytes) -> PageCommand:
    """The command of one page message; BadMessage when it is too long, not JSON, or not a command."""
    if len(data) > MAX_MESSAGE_BYTES:
        raise BadMessage(f"a message is at most {MAX_MESSAGE_BYTES} bytes")
    try:
        message = msgspec.json.decode(data)
    except (msgspec.DecodeError, RecursionError) as exc:
        raise BadMessage(f"not JSON: {exc}") from None
    number = 0
    if isinstance(message, dict) and "id" in message:
        number = message.pop("id")
        if type(number) is not int or not 0 <= number <= MAX_ID:
            raise BadMessage(f'"id" is a whole number from 0 to 2**53 that the reply repeats, got {number!r:.40}')
    try:
        return PageCommand(number, commands.parse(message))
    except commands.BadCommand as exc:
        raise BadMessage(str(exc)) from None


def frame_point(record: dict) -> dict:
    """What the page plots of a `frame` record; its gaze_errors are those of earlier VSyncs, which the page puts at
    their own VSync's point."""
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
        "gaze_errors": [
            {k: e.get(k) for k in GAZE_ERROR_KEYS} for e in (record.get("gaze_errors") or [])[:MAX_GAZE_ERRORS]
        ],
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
