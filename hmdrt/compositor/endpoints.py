"""The compositor's three sockets (docs/architecture.md, "Bus"): the ingest SUB that drivers publish to, the
telemetry PUB (a `frame` per VSync, `stats` each second) and the control ROUTER (status, stats, set,
snapshot, shutdown).

Every queue is bounded: the ingest's receive high-water mark drops the oldest-waiting messages when
the compositor falls behind (ZeroMQ counts nothing, so the drivers' own sequence numbers reveal the
gap), malformed messages are counted, and control requests over 64 KiB or unreadable get an error
reply rather than a crash. The ingest and control sockets read within a budget per peer and per socket
(hmdrt.bus.limits): what a flooding peer sends beyond its own is refused and counted. Endpoints ending in ":*"
bind a free port; `address` says which. An ipc:// socket file is made 0600 and removed on close.

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

from hmdrt.bus import limits
from hmdrt.bus.limits import Limiter, peer, silent
from hmdrt.bus.local import ipc_path
from hmdrt.bus.messages import MAX_PAYLOAD_BYTES, MAX_TOPIC_BYTES, MalformedMessage, Status, decode, pack
from hmdrt.bus.security import LOCAL_TRANSPORTS, ClientKeys, Guard
from hmdrt.compositor.commands import NOT_A_COMMAND
from hmdrt.compositor.samples import MAX_DEVICES
from hmdrt.errors import ConfigError

POLL_MS = 50
INGEST_HWM = 10_000  # messages: several seconds of every driver at its full rate
RATE_LIMITED = msgspec.msgpack.encode(
    {
        "ok": False,
        "error": f"rate limited: at most {limits.CONTROL.per_peer_hz:g} requests a second from one client "
        f"({limits.CONTROL.burst:g} at once); ask again later",
    }
)


class _Bound:
    """A socket bound to an endpoint (a Guard's CURVE server, with one); an ipc:// socket file is made 0600 (the
    private folder already keeps others out) and removed on close."""

    def __init__(self, context: zmq.Context, kind: int, endpoint: str, guard: Guard | None):
        sock = context.socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        if guard is not None:
            guard.serve(sock)
        try:
            sock.bind(endpoint)
        except zmq.ZMQError as exc:
            sock.close()
            raise ConfigError(f"cannot bind {endpoint}: {exc} (is another hmdrt running?)") from None
        self._sock = sock
        self.address: str = sock.getsockopt(zmq.LAST_ENDPOINT).decode()
        self._file = ipc_path(self.address)
        if self._file is not None:
            os.chmod(self._file, 0o600)

    def _close_socket(self) -> None:
        self._sock.close()
        if self._file is not None:
            self._file.unlink(missing_ok=True)


class Ingest(_Bound):
    """Receives drivers' gaze, pose and status messages on a thread and hands samples to `sink`, within each
    peer's budget (hmdrt.bus.limits.INGEST). The newest status of at most MAX_DEVICES devices is kept; with that
    table full, those silent for over expiry_ns make room for a new one, else its status is refused and counted."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        sink: Callable[[str, object, int], None],
        clock,
        guard: Guard | None = None,
    ):
        super().__init__(context, zmq.SUB, endpoint, guard)
        self._sock.setsockopt(zmq.RCVHWM, INGEST_HWM)
        self._sock.setsockopt(zmq.MAXMSGSIZE, 16 * MAX_PAYLOAD_BYTES)
        self._sock.setsockopt(zmq.SUBSCRIBE, b"")
        self._sink = sink
        self._clock = clock
        self.limiter = Limiter(limits.INGEST)
        self.malformed = 0
        self.status: dict[str, Status] = {}  # the newest status of each device
        self._heard: dict[str, int] = {}  # when each of those arrived
        self.expiry_ns = 2_000_000_000  # [fallback] centre_after_ms, as the sample store's
        self.statuses_refused = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="ingest", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            if not self._sock.poll(POLL_MS):
                continue
            while not self._stop.is_set():
                wait = self.limiter.wait_s()
                if wait:
                    self._stop.wait(wait)
                    break
                try:
                    frames = self._sock.recv_multipart(zmq.NOBLOCK, copy=False)
                except zmq.Again:
                    break
                if self.limiter.admit(peer(frames[0])):
                    self._take([frame.bytes for frame in frames])

    def _take(self, frames: list[bytes]) -> None:
        try:
            kind, device, message = decode(frames)
        except MalformedMessage:
            self.malformed += 1
            return
        now = self._clock.now_ns()
        if not isinstance(message, Status):
            self._sink(device, message, now)
        elif device in self.status or len(self.status) < MAX_DEVICES or self._expire(now):
            self.status[device] = message
            self._heard[device] = now
        else:
            self.statuses_refused += 1

    def _expire(self, now_ns: int) -> bool:
        """Drop the statuses of devices silent for over expiry_ns; whether any was."""
        gone = silent(self._heard, now_ns, self.expiry_ns)
        for device in gone:
            del self.status[device], self._heard[device]
        return bool(gone)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._close_socket()


class Telemetry(_Bound):
    """Publishes frame records and stats; a subscriber that cannot keep up loses messages, not the compositor.

    An XPUB socket, so that the topics in `on_demand` (the `preview`) are made only while a client subscribes to one
    by its name: `subscribed(topic)` follows the subscription messages (the first subscriber of a topic, the last to
    leave), read whenever something is published; a subscription to every topic ("") does not ask for them."""

    def __init__(
        self, context: zmq.Context, endpoint: str, guard: Guard | None = None, on_demand: tuple[str, ...] = ()
    ):
        super().__init__(context, zmq.XPUB, endpoint, guard)
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
        self._close_socket()


class ControlServer(_Bound):
    """Answers control requests ({"cmd": ...} msgpack maps) with handler(request) -> reply map. A command in
    `mutating` is refused and counted from a client without a CURVE identity (with a guard) or on a tcp:// socket
    without a guard. A ROUTER, as REP, to clients (REQ, or DEALER with or without the empty delimiter frame), but one
    that sees which peer each request came from: a request over its peer's budget (hmdrt.bus.limits.CONTROL) is
    answered "rate limited" and counted, without being decoded."""

    def __init__(
        self,
        context: zmq.Context,
        endpoint: str,
        handler: Callable[[dict], dict],
        mutating: frozenset[str],
        guard: Guard | None = None,
    ):
        super().__init__(context, zmq.ROUTER, endpoint, guard)
        self._sock.setsockopt(zmq.MAXMSGSIZE, 16 * MAX_PAYLOAD_BYTES)
        self.limiter = Limiter(limits.CONTROL)
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
            wait = self.limiter.wait_s()
            if wait:
                self._stop.wait(wait)
            elif self._sock.poll(POLL_MS):
                self._answer(self._sock.recv_multipart(copy=False))

    def _answer(self, frames: list[zmq.Frame]) -> None:
        """Reply to one request as it came: the peer's routing id, the empty delimiter if it sent one, the request."""
        head = 2 if len(frames) > 1 and not len(frames[1]) else 1
        envelope, body = frames[:head], frames[head:]
        if not body:
            self.bad_requests += 1  # a delimiter and nothing else: no request to answer
            return
        reply = msgspec.msgpack.encode(self._reply(body)) if self.limiter.admit(peer(body[0])) else RATE_LIMITED
        self._sock.send_multipart([*envelope, reply], copy=False)

    def close(self) -> None:
        self._stop.set()
        self._thread.join()
        self._close_socket()


def request(endpoint: str, command: dict, timeout_s: float = 2.0, keys: ClientKeys | None = None) -> dict:
    """Send one control request to a running compositor and return its reply (ConfigError if none); with keys,
    as a CURVE client (a compositor with [security] answers no other)."""
    context = zmq.Context.instance()
    sock = context.socket(zmq.REQ)
    sock.setsockopt(zmq.LINGER, 0)
    sock.setsockopt(zmq.RCVTIMEO, int(timeout_s * 1000))
    sock.setsockopt(zmq.SNDTIMEO, int(timeout_s * 1000))  # a REQ with no pipe to send on would block for good
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
