"""fove://HOST:PORT: a FOVE headset served over TCP (wire spec in drivers.protocols.fove; docs/protocols.md, FOVE).

open() connects, reads the server's hello and subscribes to eye tracking and head pose; read() turns
eye frames into Gaze and pose frames into Pose. The coordinate conversion happens here, once: FOVE's
head frame is left-handed with +Z forward, ours right-handed with -Z forward (docs/architecture.md), a mirror
image in z, so directions and positions map (x, y, z) -> (x, y, -z) and orientations (w, x, y, z) ->
(w, -x, -y, z) (protocols.fove.mirror_vector / mirror_quaternion). A gaze sample is valid when its
result is ok or Data_LowAccuracy, both eyes are Opened and its vectors are unit; Data_NoUpdate and
Data_Unreliable (lost tracking, gaze (0, 0, 1)) are invalid. Device timestamps (us) are kept as t_dev
in ns and mapped to host time; frame-id gaps count as dropped, frames that do not parse (or carry a
time past the bus's 2**62 ns) as malformed; an oversize frame or a closed connection raises DeviceLost.
"""

from __future__ import annotations

import socket

import msgspec

from hmdrt.bus.messages import Gaze, Pose, usable
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DeviceLost, Driver, DriverError, DriverUrl, Sample, SequenceGaps
from hmdrt.drivers.clocksync import ClockSync
from hmdrt.drivers.protocols import fove
from hmdrt.drivers.protocols.fove import Capability, EyeState, Result
from hmdrt.errors import ConfigError

GAZE_CAPS = Capability.EYE_TRACKING | Capability.GAZE_DEPTH
POSE_CAPS = Capability.ORIENTATION | Capability.POSITION
VALID_RESULTS = (Result.OK, Result.DATA_LOW_ACCURACY)
MAX_T_DEV_NS = 2**62  # the bus's time range


class FoveDriver(Driver):
    scheme = "fove"
    grammar = (
        "fove://HOST:PORT?timeout=S&pose=0|1&device_latency=MS&name=DEVICE (defaults timeout=2 for connecting "
        "and the hello, pose=1 to subscribe to head pose, device_latency=20: eye frames' capture-to-send delay)"
    )
    options = {"timeout": (float, 2.0, 0.05, 60.0), "pose": (bool, True, None, None)}
    device_latency_ms = 20.0  # FOVE's eye-tracking latency (docs/protocols.md, FOVE); poses have none

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        super().__init__(url, clock)
        if not self.url.port:
            raise ConfigError(f"fove:// needs a HOST:PORT, got {self.url.text!r}; expected {self.grammar}")
        self.address = (self.url.host or "127.0.0.1", self.url.port)
        self.hello: fove.Hello | None = None
        self._sock: socket.socket | None = None

    def open(self) -> None:
        host, port = self.address
        try:
            self._sock = socket.create_connection(self.address, timeout=self.opt["timeout"])
        except OSError as exc:
            raise DeviceLost(f"fove://{host}:{port}: cannot connect ({exc})") from None
        self._reader = fove.FrameReader()
        self._pending: list[tuple[bytes, int]] = []  # frame payloads with their receive times
        self._eye_ids, self._pose_ids = SequenceGaps(), SequenceGaps()
        # Poses arrive with less latency than eye frames: fed into one estimate, the interleaved
        # streams would look like a device clock stepping back, so poses get an estimate of their own.
        self._pose_sync = ClockSync()
        self.hello = self._hello()
        if not self.hello.capabilities & Capability.EYE_TRACKING:
            self.close()
            raise DriverError(f"fove://{host}:{port} does not offer eye tracking")
        wanted = GAZE_CAPS | (POSE_CAPS if self.opt["pose"] else 0)
        try:
            self._sock.sendall(fove.encode(fove.Subscribe(int(self.hello.capabilities & wanted))))
        except OSError as exc:
            raise self._lost(f"subscribe failed ({exc})") from None
        self.state = "connected"

    def _hello(self) -> fove.Hello:
        deadline = self.clock.now_ns() + int(self.opt["timeout"] * 1e9)
        while not self._pending:
            if not self._receive(deadline):
                raise self._lost(f"no hello within {self.opt['timeout']} s")
        try:
            record = fove.decode(self._pending.pop(0)[0])
        except fove.FrameError as exc:
            self.counters.malformed += 1
            record = exc
        if not isinstance(record, fove.Hello):
            self.close()
            raise DriverError(f"fove://{self.address[0]}:{self.address[1]} did not start with a hello: {record}")
        return record

    def read(self, timeout_s: float) -> list[Sample]:
        deadline = self.clock.now_ns() + int(timeout_s * 1e9)
        while True:
            out = [s for payload, t_recv in self._pending if (s := self._sample(payload, t_recv)) is not None]
            self._pending.clear()
            if out or not self._receive(deadline):
                return self.count(out)

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
        self.state = "closed"

    def _receive(self, deadline_ns: int) -> bool:
        """Wait until deadline for bytes and queue the frames they complete; False when none came."""
        if self._sock is None:
            raise DeviceLost(f"fove://{self.address[0]}:{self.address[1]} is not connected")
        self._sock.settimeout(max(deadline_ns - self.clock.now_ns(), 0) / 1e9)
        try:
            data = self._sock.recv(65536)
        except (TimeoutError, BlockingIOError):
            return False
        except OSError as exc:
            raise self._lost(f"connection failed ({exc})") from None
        if not data:
            raise self._lost("the server closed the connection")
        t_recv = self.clock.now_ns()
        try:
            payloads = self._reader.feed(data)
        except fove.FrameTooLarge as exc:
            self.counters.malformed += 1
            raise self._lost(str(exc)) from None
        self._pending += [(payload, t_recv) for payload in payloads]
        return True

    def _lost(self, why: str) -> DeviceLost:
        self.close()
        self.state = "lost"
        return DeviceLost(f"fove://{self.address[0]}:{self.address[1]}: {why}")

    def _sample(self, payload: bytes, t_recv: int) -> Sample | None:
        try:
            record = fove.decode(payload)
        except fove.FrameError:
            record = None
        if isinstance(record, fove.Eye | fove.Pose) and record.timestamp * 1000 > MAX_T_DEV_NS:
            record = None  # a u64 microsecond time the bus cannot carry (nor msgpack, past 2**64 ns)
        if isinstance(record, fove.Eye):
            return self._gaze(record, t_recv)
        if isinstance(record, fove.Pose):
            return self._pose(record, t_recv)
        self.counters.malformed += 1  # garbage, a record the server should not send now, or a time out of range
        return None

    def _gaze(self, eye: fove.Eye, t_recv: int) -> Gaze:
        self.counters.dropped += self._eye_ids.see(eye.id)
        t_dev = eye.timestamp * 1000
        opened = eye.state_left == eye.state_right == EyeState.OPENED
        gaze = Gaze(
            seq=eye.id,
            t_host=self.sync.add(t_dev, t_recv),
            t_dev=t_dev,
            valid=eye.result in VALID_RESULTS and opened,
            C=fove.mirror_vector(eye.ray_direction),
            L=fove.mirror_vector(eye.gaze_left),
            R=fove.mirror_vector(eye.gaze_right),
            depth_m=eye.depth or None,
        )
        return gaze if usable(gaze) or not gaze.valid else msgspec.structs.replace(gaze, valid=False)

    def _pose(self, pose: fove.Pose, t_recv: int) -> Pose:
        self.counters.dropped += self._pose_ids.see(pose.id)
        t_dev = pose.timestamp * 1000
        sample = Pose(
            seq=pose.id,
            t_host=self._pose_sync.add(t_dev, t_recv),
            position=fove.mirror_vector(pose.position),
            orientation=fove.from_fove_quaternion(pose.orientation),
            t_dev=t_dev,
        )
        return sample if usable(sample) else msgspec.structs.replace(sample, valid=False)
