"""A FOVE headset on a TCP port: eye frames at 120 Hz and head poses at 70 Hz (docs/protocols.md, FOVE).

Speaks the framing and records of drivers.protocols.fove (the wire spec is in its docstring). Gaze
comes from a GazeFeed, converted to FOVE's left-handed frame; a blink or an invalid sample goes out
as FOVE reports lost tracking: gaze (0, 0, 1), both eyes Closed, result Data_Unreliable. Eye frames
leave about 20 ms after capture by default, FOVE's measured latency (section 2). The head turns as
replay.synthetic's head model does (or stays still), sampled at the 70 Hz display rate.

One thread serves every client with a selector: it sends hello on connect, serves each client what
it subscribed to, counts malformed client frames, and drops a client that disconnects or sends an
oversize frame. A client that does not read loses frames (counted in `dropped`) rather than stalling
the others.
"""

from __future__ import annotations

import selectors
import socket
from dataclasses import dataclass, field

from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.emulators.base import Emulated, EmulatorOptions, NetworkEmulator
from hmdrt.drivers.emulators.feed import FeedSample, GazeFeed
from hmdrt.drivers.protocols.fove import (
    API_VERSION,
    DISPLAY_RATE_HZ,
    EYE_RATE_HZ,
    LOST_GAZE,
    Capability,
    Eye,
    EyeState,
    FrameError,
    FrameReader,
    FrameTooLarge,
    Hello,
    Pose,
    Record,
    Result,
    Subscribe,
    decode,
    encode,
    mirror_vector,
    to_fove_quaternion,
)
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource
from hmdrt.spatial import mean_direction, quat_from_yaw_pitch

OFFERED = Capability.ORIENTATION | Capability.POSITION | Capability.EYE_TRACKING | Capability.GAZE_DEPTH
POSE_CAPS = Capability.ORIENTATION | Capability.POSITION
PORT = 50050  # where `hmdrt emulate fove` serves by default
LATENCY_MS = 20.0  # the emulated capture-to-send latency by default
MAX_CLIENTS = 16
MAX_OUTBOX_BYTES = 256 * 1024  # several seconds of frames for a client that stopped reading
POSE_PERIOD_NS = 1e9 / DISPLAY_RATE_HZ


@dataclass
class _Client:
    sock: socket.socket
    reader: FrameReader = field(default_factory=FrameReader)
    outbox: bytearray = field(default_factory=bytearray)
    capabilities: int = 0


def eye_record(sample: FeedSample, timestamp_us: int) -> Eye:
    """A feed sample (our head frame) as a FOVE eye frame; an invalid one as lost tracking."""
    centre = mean_direction(sample.left, sample.right) if sample.valid else None
    if centre is not None:
        left, right, ray = (mirror_vector(v) for v in (sample.left, sample.right, centre))
        state, result, depth = EyeState.OPENED, Result.OK, sample.depth_m
    else:
        left = right = ray = LOST_GAZE
        state, result, depth = EyeState.CLOSED, Result.DATA_UNRELIABLE, None
    return Eye(
        id=sample.index,
        timestamp=timestamp_us,
        gaze_left=left,
        gaze_right=right,
        state_left=state,
        state_right=state,
        ray_origin=(0.0, 0.0, 0.0),
        ray_direction=ray,
        depth=depth,
        result=result,
    )


class FoveEmulator(NetworkEmulator):
    """Serves emulated FOVE eye and pose frames on host:port (0 = any free port; see `address`)."""

    name = "fove"
    emulates = (Emulated("fove", rate_hz=EYE_RATE_HZ, port=PORT, latency_ms=LATENCY_MS),)

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        feed: GazeFeed | None = None,
        latency_ms: float = LATENCY_MS,
        clock: Clock = MONOTONIC,
        head: bool = True,
        seed: int = 0,
    ):
        """feed: the gaze source (default: synthetic gaze of `seed` at 120 Hz with latency_ms of latency;
        a given feed brings its own rate and latency). head: synthetic head motion of `seed`, else still."""
        super().__init__(host, port, clock)
        self.feed = feed if feed is not None else GazeFeed(EYE_RATE_HZ, seed=seed, latency_ms=latency_ms, clock=clock)
        self.head = SyntheticSource(SyntheticConfig(seed=seed, head=True)) if head else None
        self.malformed = 0  # client frames that did not parse, or were oversize
        self.dropped = 0  # frames not queued for a client that stopped reading
        self._clients: dict[socket.socket, _Client] = {}

    @classmethod
    def emulate(cls, device: Emulated, options: EmulatorOptions) -> FoveEmulator:
        """At the device's port unless another is asked for, gaze from options.feed, head motion of the seed."""
        port = options.port_for(device)
        return cls(options.host, port, feed=options.feed(device), clock=options.clock, seed=options.seed)

    @property
    def clients(self) -> int:
        return len(self._clients)

    def _bind(self) -> None:
        self._listener = socket.create_server((self.host, self.port))
        self._listener.setblocking(False)
        self._address = self._listener.getsockname()[:2]
        self._selector = selectors.DefaultSelector()
        self._selector.register(self._listener, selectors.EVENT_READ)
        self.epoch_ns = self.clock.now_ns()  # the host time the device clock counts microseconds from
        self._eyes = self.feed.samples()
        self._eye = next(self._eyes)
        self._pose_k = 0

    def _release(self) -> None:
        for client in list(self._clients.values()):
            self._drop(client)
        self._selector.close()
        self._listener.close()

    def _tick(self, now_ns: int) -> int:
        while (eye := self._eye).due_ns <= now_ns:
            timestamp_us = max(0, eye.capture_ns - self.epoch_ns) // 1000
            self._broadcast(eye_record(eye, timestamp_us), Capability.EYE_TRACKING)
            self._log_sent(timestamp_us * 1000)
            self._eye = next(self._eyes)
        while (pose_ns := round(self._pose_k * POSE_PERIOD_NS)) <= now_ns - self.epoch_ns:
            self._broadcast(self._pose(self._pose_k, pose_ns // 1000), POSE_CAPS)
            self._pose_k += 1
        return min(self._eye.due_ns, self.epoch_ns + pose_ns)

    def _poll(self, timeout_s: float) -> None:
        for key, events in self._selector.select(timeout_s):
            if key.fileobj is self._listener:
                self._accept()
            elif key.fileobj in self._clients:
                self._service(self._clients[key.fileobj], events)

    def _pose(self, k: int, timestamp_us: int) -> Pose:
        q = (1.0, 0.0, 0.0, 0.0)
        if self.head is not None:
            q = quat_from_yaw_pitch(*self.head.head_pose(k / DISPLAY_RATE_HZ))
        return Pose(id=k, timestamp=timestamp_us, orientation=to_fove_quaternion(q), position=(0.0, 0.0, 0.0))

    def _accept(self) -> None:
        try:
            sock, _ = self._listener.accept()
        except OSError:
            return
        if len(self._clients) >= MAX_CLIENTS:
            sock.close()
            return
        sock.setblocking(False)
        client = self._clients[sock] = _Client(sock)
        self._selector.register(sock, selectors.EVENT_READ)
        self._queue(client, encode(Hello(API_VERSION, int(OFFERED), self.feed.rate_hz, DISPLAY_RATE_HZ)))

    def _service(self, client: _Client, events: int) -> None:
        if events & selectors.EVENT_WRITE:
            self._flush(client)
        if not events & selectors.EVENT_READ or client.sock not in self._clients:
            return
        try:
            data = client.sock.recv(65536)
            payloads = client.reader.feed(data)
        except FrameTooLarge:
            self.malformed += 1
            data = b""
        except OSError:
            data = b""
        if not data:
            self._drop(client)
            return
        for payload in payloads:
            try:
                record = decode(payload)
            except FrameError:
                record = None
            if isinstance(record, Subscribe):
                client.capabilities = record.capabilities & OFFERED
            else:  # garbage, or a record only the server sends
                self.malformed += 1

    def _broadcast(self, record: Record, capabilities: int) -> None:
        frame = None
        for client in list(self._clients.values()):
            if client.capabilities & capabilities:
                frame = frame or encode(record)
                self._queue(client, frame)

    def _queue(self, client: _Client, frame: bytes) -> None:
        if len(client.outbox) + len(frame) > MAX_OUTBOX_BYTES:
            self.dropped += 1
            return
        client.outbox += frame
        self._flush(client)

    def _flush(self, client: _Client) -> None:
        """Send what the socket takes now; watch for writability while anything is left."""
        try:
            del client.outbox[: client.sock.send(client.outbox)]
        except BlockingIOError:
            pass
        except OSError:
            self._drop(client)
            return
        events = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.outbox else 0)
        if self._selector.get_key(client.sock).events != events:
            self._selector.modify(client.sock, events)

    def _drop(self, client: _Client) -> None:
        self._clients.pop(client.sock, None)
        self._selector.unregister(client.sock)
        client.sock.close()
