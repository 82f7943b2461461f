"""The watch server's connection to one compositor: its telemetry (SUB) in, control requests (REQ) out, both as a
CURVE client when given keys (a compositor with [security] answers no other).

The SUB takes `frame`, `stats` and `log` always and `preview` only while a page is open (want_previews): the
compositor makes previews only while someone subscribes to them by name. Messages over MAX_TELEMETRY_BYTES or that
do not decode are counted and skipped. Control requests go one at a time, each on a fresh REQ socket (one that
timed out cannot be used again), and a compositor that does not answer is a reply with "ok": false.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator

import msgspec
import zmq
import zmq.asyncio

from hmdrt.bus.security import ClientKeys
from hmdrt.compositor.commands import Status, to_request
from hmdrt.compositor.preview import PREVIEW
from hmdrt.errors import ConfigError

log = logging.getLogger(__name__)

STATUS = to_request(Status())  # the request the watch polls the compositor with

TOPICS = (b"frame", b"stats", b"log")
MAX_TELEMETRY_BYTES = 4 * 1024 * 1024  # a stats report or a preview fits many times over
CONTROL_TIMEOUT_S = 2.0


class CompositorLink:
    """A compositor's telemetry and control socket, for one event loop."""

    def __init__(self, control: str, keys: ClientKeys | None = None, timeout_s: float = CONTROL_TIMEOUT_S):
        self.control, self.keys, self.timeout_s = control, keys, timeout_s
        self.telemetry = ""
        self._context = zmq.asyncio.Context()
        self._sub = self._socket(zmq.SUB)
        self._sub.setsockopt(zmq.MAXMSGSIZE, MAX_TELEMETRY_BYTES)
        self._sub.setsockopt(zmq.RCVHWM, 1000)
        for topic in TOPICS:
            self._sub.setsockopt(zmq.SUBSCRIBE, topic)
        self._previews = False
        self._lock = asyncio.Lock()
        self.malformed = 0  # telemetry messages that did not decode

    def _socket(self, kind: int) -> zmq.asyncio.Socket:
        sock = self._context.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        if self.keys is not None:
            self.keys.apply(sock)
        return sock

    async def connect(self, telemetry: str = "") -> None:
        """Subscribe to `telemetry`, or ("") to the endpoint the compositor's status names; ConfigError when it
        has to be asked and does not answer."""
        if not telemetry:
            reply = await self.request(STATUS)
            telemetry = reply.get("endpoints", {}).get("telemetry") if reply.get("ok") else None
            if not isinstance(telemetry, str):
                raise ConfigError(f"no telemetry endpoint from the compositor: {reply.get('error')} (give --telemetry)")
        try:
            self._sub.connect(telemetry)
        except zmq.ZMQError as exc:
            raise ConfigError(f"cannot connect to the telemetry at {telemetry}: {exc}") from None
        self.telemetry = telemetry

    def want_previews(self, wanted: bool) -> None:
        """Subscribe to the compositor's previews, or leave them (it then stops making them)."""
        if wanted != self._previews:
            self._sub.setsockopt(zmq.SUBSCRIBE if wanted else zmq.UNSUBSCRIBE, PREVIEW.encode())
            self._previews = wanted

    async def messages(self) -> AsyncIterator[tuple[str, dict]]:
        """(topic, fields) of each telemetry message, as they arrive."""
        while True:
            frames = await self._sub.recv_multipart()
            try:
                if len(frames) != 2:
                    raise ValueError(f"{len(frames)} frames")
                fields = msgspec.msgpack.decode(frames[1])
                if not isinstance(fields, dict):
                    raise ValueError("not a map")
                yield frames[0].decode("ascii"), fields
            except (ValueError, RecursionError) as exc:  # msgspec.DecodeError and UnicodeDecodeError are ValueErrors
                self.malformed += 1
                log.debug("telemetry message skipped: %s", exc)

    async def request(self, command: dict) -> dict:
        """The compositor's reply to a control request; {"ok": False, "error": ...} when none comes in time."""
        async with self._lock:
            sock = None
            try:  # a socket of its own, which even this process being out of files only makes a failed request
                sock = self._socket(zmq.REQ)
                sock.setsockopt(zmq.MAXMSGSIZE, MAX_TELEMETRY_BYTES)
                sock.connect(self.control)
                await sock.send(msgspec.msgpack.encode(command))
                reply = msgspec.msgpack.decode(await asyncio.wait_for(sock.recv(), self.timeout_s))
            except TimeoutError:
                return {"ok": False, "error": f"no hmdrt compositor answered at {self.control} in {self.timeout_s:g} s"}
            except (zmq.ZMQError, ValueError, RecursionError) as exc:
                return {"ok": False, "error": f"control request to {self.control} failed: {exc}"}
            finally:
                if sock is not None:
                    sock.close()
        return reply if isinstance(reply, dict) else {"ok": False, "error": "the compositor's reply is not a map"}

    def close(self) -> None:
        self._sub.close()
        self._context.term()
