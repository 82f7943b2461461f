"""The compositor's three sockets (docs/architecture.md, "Bus"): the ingest SUB that drivers publish to, the
telemetry PUB (a `frame` per VSync, `stats` each second) and the control REP (status, stats, set,
snapshot, shutdown).

Every queue is bounded: the ingest's receive high-water mark drops the oldest-waiting messages when
the compositor falls behind (ZeroMQ counts nothing, so the drivers' own sequence numbers reveal the
gap), malformed messages are counted, and control requests over 64 KiB or unreadable get an error
reply rather than a crash. Endpoints ending in ":*" bind a free port; `address` says which.

With a Guard (hmdrt.bus.security) every socket is a CURVE server that admits only allowed client keys,
and the control socket answers the commands that change the compositor (hmdrt.compositor.control says which)
only for a client that authenticated; without one the sockets bind loopback only, and those commands are
answered on an ipc:// control socket (a private folder's: hmdrt.bus.local) but refused on a tcp:// one, which
every user of the machine can reach.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Callable

import msgspec
import zmq

from hmdrt.bus.local import ipc_path
from hmdrt.bus.messages import MAX_PAYLOAD_BYTES, MAX_TOPIC_BYTES, MalformedMessage, Status, decode, pack
from hmdrt.bus.security import LOCAL_TRANSPORTS, ClientKeys, Guard
from hmdrt.compositor.commands import NOT_A_COMMAND
from hmdrt.errors import ConfigError

POLL_MS = 50
INGEST_HWM = 10_000  # messages: several seconds of every driver at its full rate


def _bind(context: zmq.Context, kind: int, endpoint: str, guard: Guard | None = None) -> tuple[zmq.Socket, str]:
    sock = context.socket(kind)
    sock.setsockopt(zmq.LINGER, 0)
    if guard is not None:
        guard.serve(sock)
    try:
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        sock.close()
        raise ConfigError(f"cannot bind {endpoint}: {exc} (is another hmdrt running?)") from None
    return sock, sock.getsockopt(zmq.LAST_ENDPOINT).decode()


class Ingest:
    """Receives drivers' gaze, pose and status messages on a thread and hands samples to `sink`."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        sink: Callable[[str, object, int], None],
        clock,
        guard: Guard | None = None,
    ):
        self._sock, self.address = _bind(context, zmq.SUB, endpoint, guard)
        self._sock.setsockopt(zmq.RCVHWM, INGEST_HWM)
        self._sock.setsockopt(zmq.MAXMSGSIZE, 16 * MAX_PAYLOAD_BYTES)
        self._sock.setsockopt(zmq.SUBSCRIBE, b"")
        self._sink = sink
        self._clock = clock
        self.malformed = 0
        self.status: dict[str, Status] = {}  # the newest status of each device
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ingest", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self._sock.poll(POLL_MS):
                continue
            while True:
                try:
                    frames = self._sock.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                try:
                    kind, device, message = decode(frames)
                except MalformedMessage:
                    self.malformed += 1
                    continue
                if isinstance(message, Status):
                    self.status[device] = message
                else:
                    self._sink(device, message, self._clock.now_ns())

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._sock.close()


class Telemetry:
    """Publishes frame records and stats; a subscriber that cannot keep up loses messages, not the compositor.

    An XPUB socket, so that the topics in `on_demand` (the `preview`) are made only while a client subscribes to one
    by its name: `subscribed(topic)` follows the subscription messages (the first subscriber of a topic, the last to
    leave), read whenever something is published; a subscription to every topic ("") does not ask for them."""

    def __init__(
        self, context: zmq.Context, endpoint: str, guard: Guard | None = None, on_demand: tuple[str, ...] = ()
    ):
        self._sock, self.address = _bind(context, zmq.XPUB, endpoint, guard)
        self._sock.setsockopt(zmq.SNDHWM, 1000)
        self._sock.setsockopt(zmq.MAXMSGSIZE, 1 + MAX_TOPIC_BYTES)  # a subscription message: a flag byte and a topic
        self._on_demand = {topic.encode(): False for topic in on_demand}
        self._lock = threading.Lock()

    def subscribed(self, topic: str) -> bool:
        """Whether a client subscribes to an on-demand topic by name."""
        return self._on_demand.get(topic.encode(), False)

    def publish(self, topic: str, fields: dict) -> None:
        with self._lock:
            while self._sock.getsockopt(zmq.EVENTS) & zmq.POLLIN:  # subscription messages: flag 1 or 0, topic
                message = self._sock.recv(zmq.NOBLOCK)
                if message[1:] in self._on_demand:
                    self._on_demand[message[1:]] = message[:1] == b"\x01"
            try:
                self._sock.send_multipart(pack(topic.encode(), fields), flags=zmq.NOBLOCK)
            except zmq.Again:
                pass

    def close(self) -> None:
        self._sock.close()


class ControlServer:
    """Answers control requests ({"cmd": ...} msgpack maps) with handler(request) -> reply map. A command in
    `mutating` is refused and counted from a client without a CURVE identity (with a guard) or on a tcp:// socket
    without a guard; an ipc:// socket file is made 0600 and removed on close."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        handler: Callable[[dict], dict],
        mutating: frozenset[str],
        guard: Guard | None = None,
    ):
        self._sock, self.address = _bind(context, zmq.REP, endpoint, guard)
        self._file = ipc_path(self.address)
        if self._file is not None:
            os.chmod(self._file, 0o600)
        self._handler = handler
        self._mutating = mutating
        self._require_identity = guard is not None
        # loopback tcp without CURVE: any user of the machine can connect, so it may only read
        self._read_only = guard is None and endpoint.partition("://")[0] not in LOCAL_TRANSPORTS
        self.bad_requests = 0
        self.unauthorised = 0  # mutating commands refused: no CURVE identity, or tcp:// without CURVE
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="control", daemon=True)
        self._thread.start()

    @staticmethod
    def identity(frame: zmq.Frame) -> str:
        """The CURVE client key a request came with ("" for a client that did not authenticate)."""
        try:
            return frame.get("User-Id")
        except zmq.ZMQError:
            return ""

    def _reply(self, frames: list[zmq.Frame]) -> dict:
        if len(frames) != 1 or len(frames[0]) > MAX_PAYLOAD_BYTES:
            self.bad_requests += 1
            return {"ok": False, "error": f"a request is one msgpack map of at most {MAX_PAYLOAD_BYTES} bytes"}
        try:
            request = msgspec.msgpack.decode(frames[0].buffer)
        except (msgspec.DecodeError, RecursionError):  # msgspec's guard against nesting deeper than Python's
            request = None
        if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
            self.bad_requests += 1
            return {"ok": False, "error": NOT_A_COMMAND}
        refusal = self._refusal(frames[0]) if request["cmd"] in self._mutating else ""
        if refusal:
            self.unauthorised += 1
            return {"ok": False, "error": f"{request['cmd']} {refusal}"}
        return self._handler(request)

    def _refusal(self, frame: zmq.Frame) -> str:
        """Why a command that changes the compositor may not run for this request ("": it may)."""
        if self._read_only:
            return (
                "is refused on a tcp:// control socket without [security], which every local user can reach; "
                "use the default ipc:// one (yours alone) or CURVE keys"
            )
        if self._require_identity and not self.identity(frame):
            return "needs an authenticated (CURVE) client"
        return ""

    def _run(self) -> None:
        while not self._stop.is_set():
            if self._sock.poll(POLL_MS):
                reply = self._reply(self._sock.recv_multipart(copy=False))
                self._sock.send(msgspec.msgpack.encode(reply))

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._sock.close()
        if self._file is not None:
            self._file.unlink(missing_ok=True)


def request(endpoint: str, command: dict, timeout_s: float = 2.0, keys: ClientKeys | None = None) -> dict:
    """Send one control request to a running compositor and return its reply (ConfigError if none); with keys,
    as a CURVE client (a compositor with [security] answers no other)."""
    context = zmq.Context.instance()
    sock = context.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, int(timeout_s * 1000))
    sock.setsockopt(zmq.MAXMSGSIZE, 16 * MAX_PAYLOAD_BYTES)
    if keys is not None:
        keys.apply(sock)
    try:
        sock.connect(endpoint)
        sock.send(msgspec.msgpack.encode(command))
        return msgspec.msgpack.decode(sock.recv())
    except zmq.Again:
        hint = "" if keys else " (one with [security] answers only clients with --server-key and --client-key)"
        raise ConfigError(f"no hmdrt compositor answered at {endpoint} within {timeout_s:g} s{hint}") from None
    except (zmq.ZMQError, msgspec.DecodeError, RecursionError) as exc:
        raise ConfigError(f"control request to {endpoint} failed: {exc}") from None
    finally:
        sock.close()
