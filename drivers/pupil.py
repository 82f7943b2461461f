"""pupil://HOST:PORT: Pupil Core gaze through Pupil Remote and the IPC backbone (docs/protocols.md, Pupil).

open() asks Pupil Remote (ZeroMQ REQ/REP, default port 50020) for the backbone's SUB_PORT, measures
the offset of Pupil time from the host clock with `t` (round-trip corrected, as Pupil's own time sync
does: offset = t_pupil - (t_send + rtt / 2), docs/protocols.md, Pupil) and subscribes to "gaze.3d."
on the backbone. read() decodes the msgpack gaze datums of section 3.2 and converts them once, here:
Pupil's 3D camera space is OpenCV's (x right, y down, z forward, mm), ours is right-handed with +Y up
and -Z forward (docs/architecture.md), so vectors map (x, y, z) -> (x, -y, -z), a half turn about X. Eye 0 is the
right eye (section 3.2): binocular "gaze.3d.01." gives R from gaze_normals_3d[0] and L from [1] (keyed by
the integers 0 and 1 up to Capture 2.6, by the strings "0" and "1" from 3.0); monocular "gaze.3d.0." /
"gaze.3d.1." give R / L from gaze_normal_3d. C is the mean of the eyes, depth_m the distance of
gaze_point_3d (mm -> m), valid = confidence >= 0.6 (section 3.2's pairing threshold). t_dev is Pupil time
in ns.

Any client may rebase Pupil time with `T` (Pupil's own example scripts send `T 0.0`). When the clock sync
sees Pupil time jump, or a datum's timestamp no longer fits the measured offset, the driver measures the
offset again with `t`; without that, one-way receive times would put every later t_host late by the whole
capture-to-receipt delay. Each rebase is counted (`rebases`) and logged. When the stream stays silent for
`timeout` seconds the driver asks Pupil Remote for the time again; no answer raises DeviceLost.
"""

from __future__ import annotations

import logging
from typing import Annotated, Literal

import msgspec
import numpy as np
import zmq

from hmdrt.bus.messages import Gaze
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DeviceLost, Driver, DriverError, DriverUrl, Sample
from hmdrt.ranges import Finite
from hmdrt.spatial import mean_direction

DEFAULT_PORT = 50020
GAZE_TOPIC = "gaze.3d."
MIN_CONFIDENCE = 0.6
MAX_DATUM_BYTES = 64 * 1024
MAX_ZMQ_MESSAGE = 16 * MAX_DATUM_BYTES  # libzmq disconnects a peer that sends more: a hard memory cap
MAX_BATCH = 10_000  # messages taken per read(), so a flood cannot hold read() forever
TIME_PROBES = 3  # `t` round trips per offset measurement; the fastest is kept
MAX_TIME_NS = 2**62  # the bus's time range
MAX_DEPTH_M = 1e6  # the bus's vergence depth range (hmdrt.bus.messages.Gaze.depth_m)
CLOCK_SLACK_NS = 20_000_000  # how far a datum may map past its receipt, or the offset move, without meaning a rebase
MAX_LAG_NS = 500_000_000  # capture-to-receipt delay past which a datum makes the driver check the offset again

log = logging.getLogger(__name__)

Vec3 = tuple[Finite, Finite, Finite]
EyeKey = Literal[0, 1, "0", "1"]  # Capture 1.x-2.6 key eyes by the msgpack integers 0 and 1, 3.0 on by "0" and "1"


class GazeDatum(msgspec.Struct, frozen=True):
    """The keys of a Pupil gaze datum the driver reads (section 3.2); other keys are ignored."""

    confidence: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
    timestamp: Finite  # Pupil time, seconds
    gaze_point_3d: Vec3 | None = None  # mm, camera space
    gaze_normals_3d: dict[EyeKey, Vec3] | None = None  # binocular, keyed by eye id
    gaze_normal_3d: Vec3 | None = None  # monocular


class MalformedDatum(ValueError):
    """A backbone message that is not a readable gaze datum."""


_decoder = msgspec.msgpack.Decoder(GazeDatum)


def opencv_head(v) -> np.ndarray:
    """A vector between OpenCV camera space and our head frame: (x, y, z) -> (x, -y, -z); its own inverse."""
    x, y, z = np.asarray(v, dtype=np.float64)
    return np.array([x, -y, -z])


def _unit(v: Vec3) -> np.ndarray:
    norm = float(np.linalg.norm(v))
    if norm < 1e-9:
        raise MalformedDatum("zero gaze normal")
    return opencv_head(v) / norm


def _by_eye(keyed: dict[EyeKey, Vec3] | None) -> dict[int, Vec3]:
    """Binocular gaze_normals_3d by integer eye id, whichever key type the Capture version sent; MalformedDatum
    unless eyes 0 and 1 appear once each."""
    keyed = keyed or {}
    by_eye = {int(key): v for key, v in keyed.items()}
    if len(by_eye) != len(keyed) or set(by_eye) != {0, 1}:
        raise MalformedDatum(f"binocular gaze needs gaze_normals_3d for eyes 0 and 1 once each, got keys {list(keyed)}")
    return by_eye


def _tuple(v: np.ndarray | None) -> tuple[float, float, float] | None:
    return None if v is None else tuple(float(c) for c in v)


def decode_gaze(topic: bytes, payload: bytes) -> Gaze:
    """A gaze.3d.* backbone message (topic and msgpack payload) in our head frame, t_dev in Pupil time (ns)
    and t_host left equal to it until a driver maps it; MalformedDatum if unreadable."""
    if len(payload) > MAX_DATUM_BYTES:
        raise MalformedDatum(f"payload of {len(payload)} bytes exceeds {MAX_DATUM_BYTES}")
    try:
        datum = _decoder.decode(payload)
    except (msgspec.DecodeError, msgspec.ValidationError) as exc:
        raise MalformedDatum(str(exc)) from None
    except RecursionError:  # an ignored key's value nested deeper than msgspec follows
        raise MalformedDatum("payload nested too deeply") from None
    eyes = {b"gaze.3d.01.": "01", b"gaze.3d.0.": "0", b"gaze.3d.1.": "1"}.get(bytes(topic))
    if eyes == "01":
        normals = _by_eye(datum.gaze_normals_3d)
        right, left = _unit(normals[0]), _unit(normals[1])
        centre = mean_direction(left, right)
        if centre is None:
            raise MalformedDatum("the eyes' gaze normals point in opposite directions")
    elif eyes is not None:
        if datum.gaze_normal_3d is None:
            raise MalformedDatum("monocular gaze needs gaze_normal_3d")
        normal = _unit(datum.gaze_normal_3d)
        right, left = (normal, None) if eyes == "0" else (None, normal)
        centre = normal
    else:
        raise MalformedDatum(f"not a 3D gaze topic: {bytes(topic)[:64]!r}")
    depth_m = None
    if datum.gaze_point_3d is not None:
        depth_m = float(np.linalg.norm(datum.gaze_point_3d)) / 1000.0 or None
        if depth_m is not None and depth_m > MAX_DEPTH_M:
            raise MalformedDatum(f"gaze_point_3d is {depth_m:.3g} m away, beyond {MAX_DEPTH_M:g} m")
    t_dev = round(datum.timestamp * 1e9)
    return Gaze(
        seq=0,
        t_host=t_dev,
        t_dev=t_dev,
        valid=datum.confidence >= MIN_CONFIDENCE,
        C=_tuple(centre),
        L=_tuple(left),
        R=_tuple(right),
        depth_m=depth_m,
    )


class PupilDriver(Driver):
    scheme = "pupil"
    grammar = (
        "pupil://HOST[:PORT]?timeout=S&name=DEVICE (defaults port 50020, timeout=1: how long Pupil Remote "
        "may take to answer, and how long the gaze stream may stay silent before the driver checks on it)"
    )
    options = {"timeout": (float, 1.0, 0.05, 60.0)}

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        super().__init__(url, clock)
        self.address = (self.url.host or "127.0.0.1", self.url.port or DEFAULT_PORT)
        self.offset_ns: int | None = None  # Pupil time minus host time, from the fastest `t` round trip
        self.rtt_ns: int | None = None
        self.rebases = 0  # times Pupil time was found rebased (a `T` from some client) and the offset measured again
        self._queued_until: int | None = None  # Pupil time (ns) up to which late datums were found queued, not rebased
        self._remote: zmq.Socket | None = None
        self._sub: zmq.Socket | None = None
        self._seq = 0

    def _socket(self, kind: int) -> zmq.Socket:
        sock = zmq.Context.instance().socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_ZMQ_MESSAGE)
        return sock

    def open(self) -> None:
        host, port = self.address
        timeout_ms = round(self.opt["timeout"] * 1000)
        self._remote = self._socket(zmq.REQ)
        self._remote.setsockopt(zmq.RCVTIMEO, timeout_ms)
        self._remote.setsockopt(zmq.SNDTIMEO, timeout_ms)
        self._remote.connect(f"tcp://{host}:{port}")
        sub_port = self._ask("SUB_PORT")
        if not (sub_port.isdigit() and 0 < int(sub_port) < 65536):
            self.close()
            raise DriverError(f"pupil://{host}:{port} answered SUB_PORT with {sub_port[:64]!r}, not a port")
        self._measure_offset()
        self._queued_until = None
        self._sub = self._socket(zmq.SUB)
        self._sub.setsockopt(zmq.SUBSCRIBE, GAZE_TOPIC.encode())
        self._sub.connect(f"tcp://{host}:{sub_port}")
        self._heard_ns = self.clock.now_ns()
        self.state = "connected"

    def read(self, timeout_s: float) -> list[Sample]:
        if self._sub is None:
            raise DeviceLost(f"pupil://{self.address[0]}:{self.address[1]} is not connected")
        out: list[Sample] = []
        if self._sub.poll(max(round(timeout_s * 1000), 0)):
            for _ in range(MAX_BATCH):
                try:
                    frames = self._sub.recv_multipart(zmq.NOBLOCK)
                except zmq.Again:
                    break
                sample = self._sample(frames, self.clock.now_ns())
                if sample is not None:
                    out.append(sample)
            self._heard_ns = self.clock.now_ns()
        elif self.clock.now_ns() - self._heard_ns > self.opt["timeout"] * 1e9:
            self._measure_offset()  # DeviceLost when Pupil Remote is gone too
            self._heard_ns = self.clock.now_ns()
        return self.count(out)

    def close(self) -> None:
        for sock in (self._remote, self._sub):
            if sock is not None:
                sock.close(linger=0)
        self._remote = self._sub = None
        self.state = "closed"

    def _ask(self, command: str) -> str:
        """Pupil Remote's reply to one command; DeviceLost when it does not answer in time."""
        try:
            self._remote.send_string(command)
            reply = self._remote.recv()
        except zmq.Again:
            self.close()
            self.state = "lost"
            raise DeviceLost(
                f"Pupil Remote at {self.address[0]}:{self.address[1]} did not answer {command!r} "
                f"within {self.opt['timeout']} s"
            ) from None
        return reply.decode("utf-8", errors="replace")

    def _probe(self) -> tuple[int, int, int]:
        """One `t` round trip: host send time, Pupil time and host reply time (ns); DriverError for a reply
        that is not a time."""
        t_send = self.clock.now_ns()
        reply = self._ask("t")
        t_reply = self.clock.now_ns()
        try:
            t_pupil_ns = float(reply) * 1e9
        except ValueError:
            t_pupil_ns = float("nan")
        if not np.isfinite(t_pupil_ns) or abs(t_pupil_ns) > MAX_TIME_NS:
            self.close()
            raise DriverError(f"Pupil Remote answered t with {reply[:64]!r}, not a time")
        return t_send, round(t_pupil_ns), t_reply

    def _measure_offset(self) -> bool:
        """Measure the offset with `t` round trips, keeping the fastest (it takes out the latency floor), and hand
        them to the clock sync. True when the offset moved since the last measurement beyond what the two round
        trips explain: Pupil time was rebased, so the rebase is counted and logged and the sync starts afresh."""
        probes = [self._probe() for _ in range(TIME_PROBES)]
        rtt, offset = min((reply - send, round(t_pupil - (send + reply) / 2)) for send, t_pupil, reply in probes)
        rebased = self.offset_ns is not None and (
            abs(offset - self.offset_ns) > (rtt + self.rtt_ns) // 2 + CLOCK_SLACK_NS
        )
        if rebased:
            self.rebases += 1
            log.warning(
                "pupil://%s:%d: Pupil time jumped by %+.3f s (a `T` from another client?); clock offset measured "
                "again with `t` (rebase %d)",
                *self.address,
                (offset - self.offset_ns) / 1e9,
                self.rebases,
            )
            self.sync.reset()
            self._queued_until = None
        self.rtt_ns, self.offset_ns = rtt, offset
        for probe in probes:
            self.sync.probe(*probe)
        return rebased

    def _fits_offset(self, t_dev: int, t_recv: int) -> bool:
        """Whether a datum's Pupil time agrees with the measured offset: captured no later than received (within
        half the round trip and some slack) and received within MAX_LAG_NS, unless it was found queued earlier."""
        lag = t_recv - (t_dev - self.offset_ns)
        if lag < -(self.rtt_ns // 2 + CLOCK_SLACK_NS):
            return False
        return lag <= MAX_LAG_NS or (self._queued_until is not None and t_dev <= self._queued_until)

    def _host_time(self, t_dev: int, t_recv: int) -> int:
        """A datum's capture time on the host clock. When the clock sync starts afresh (it saw Pupil time jump) or
        the datum does not fit the offset, the offset is measured again with `t`: receive times alone would put
        t_host late by the whole capture-to-receipt delay and understate gaze-to-photon latency."""
        resets = self.sync.resets
        t_host = self.sync.add(t_dev, t_recv)
        if self.offset_ns is None or (self.sync.resets == resets and self._fits_offset(t_dev, t_recv)):
            return t_host
        if self._measure_offset():
            self.sync.add(t_dev, t_recv)  # the sync starts afresh from this datum, in the new timebase
        else:  # not rebased: a late datum had waited in a queue, as may the others captured before now
            self._queued_until = self.clock.now_ns() + self.offset_ns
        return min(self.sync.to_host(t_dev), t_recv)

    def _sample(self, frames: list[bytes], t_recv: int) -> Gaze | None:
        try:
            if len(frames) < 2:
                raise MalformedDatum(f"{len(frames)} frame(s), expected topic and payload")
            gaze = decode_gaze(frames[0], frames[1])
        except MalformedDatum:
            self.counters.malformed += 1
            return None
        self._seq += 1
        return msgspec.structs.replace(gaze, seq=self._seq - 1, t_host=self._host_time(gaze.t_dev, t_recv))
