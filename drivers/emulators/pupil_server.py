"""Pupil Core on ZeroMQ: Pupil Remote (REQ/REP) and an IPC backbone publishing 3D gaze (docs/protocols.md, Pupil).

Pupil Remote answers as Pupil's pupil_remote.py does (section 3.1, the section 7 vectors): SUB_PORT,
PUB_PORT, t, T <float>, R [name], r, C, c, v, "Unknown command." for anything else, and "Message
forwarded." for a multi-part (topic + msgpack) request, which goes onto the backbone. REQ/REP needs
every request answered, so one the emulator cannot read (not UTF-8, or a forwarded payload that is
not a msgpack map) is counted in `malformed` and answered "Unknown command.".

The backbone is a PUB socket at SUB_PORT carrying the emulator's gaze, the notifications of R, r, C
and c ("notify.<subject>") and whatever clients publish to the SUB socket at PUB_PORT, as Pupil's
XSUB/XPUB proxy relays it. Gaze comes from a GazeFeed as binocular datums on "gaze.3d.01." (section
3.2 keys, as Capture 3.x sends them) in OpenCV camera space (x right, y down, z forward, mm), with the
world camera at the midpoint of the eyes and aligned with the head; eye 0 is the right eye. A blink or an
invalid sample has confidence 0.0 (section 3.2). Like Pupil, every gaze datum carries gaze_point_3d
(at the feed's depth, else Pupil's initial 500 mm) and, in base_data, the two pupil datums it was mapped
from, shaped as Capture 3.5's pye3d 0.3.0 detector publishes them; those also go out on "pupil.0.3d" and
"pupil.1.3d". Each eye camera (192x192 px, f = 140 px, Pupil Cam3's default intrinsics) faces its eye, a
half turn about y from the world camera, with the eyeball centre 35 mm in front of it; the projected
pupil ellipse is a weak-perspective approximation of pye3d's exact conic. Pupil time is host time minus a
timebase, epoch_ns (0 at start, so it reads the host's monotonic clock in seconds, as Pupil's does), that
T moves.
"""

from __future__ import annotations

import math
import time

import msgspec
import numpy as np
import zmq

from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.emulators.base import Emulated, NetworkEmulator
from hmdrt.drivers.emulators.feed import FeedSample, GazeFeed
from hmdrt.drivers.pupil import DEFAULT_PORT, MAX_ZMQ_MESSAGE, opencv_head
from hmdrt.spatial import mean_direction

VERSION = "3.5.1"
RATE_HZ = 200.0  # the emulated gaze rate by default
GAZE_TOPIC = "gaze.3d.01."
CONFIDENCE = 0.95  # of a tracked sample
IPD_MM = 63.5
GAZE_DISTANCE_MM = 500.0  # Pupil's gaze distance before it has seen the eyes converge (gazer_3d)
PUPIL_METHOD = "pye3d 0.3.0 real-time"  # the 3D detector of Capture 3.5 (pye3d pinned to 0.3.0)
EYE_RADIUS_MM = 10.392304845413264  # pye3d's eyeball model radius (_EYE_RADIUS_DEFAULT)
PUPIL_DIAMETER_MM = 4.0
EYE_IMAGE_PX = 192.0  # square eye camera images
EYE_FOCAL_PX = 140.0
EYE_CAMERA_TO_WORLD = np.diag([-1.0, 1.0, -1.0])  # rotation of each eye camera into the world camera; its own inverse
SPHERE_IN_EYE_CAMERA = np.array([0.0, 0.0, 35.0])  # eyeball centre seen from its eye camera, mm
UNKNOWN = "Unknown command."
MAX_RELAY = 1000  # messages relayed per loop, so a flood cannot starve Pupil Remote


def _floats(v) -> list[float]:
    return [float(c) for c in v]


def _eye_pixel(p: np.ndarray) -> np.ndarray:
    """A point in eye camera space (mm) in eye image pixels, origin top-left, as pye3d's projections give it."""
    return EYE_FOCAL_PX * p[:2] / p[2] + EYE_IMAGE_PX / 2


def pupil_datum(eye_id: int, gaze_normal: np.ndarray, confidence: float, timestamp_s: float) -> dict:
    """The 3D pupil datum of one eye (gaze_normal: its unit gaze in world camera space), with the keys, in the
    order, of Capture 3.5's pye3d plugin: create_pupil_datum's, then pye3d 0.3.0's _prepare_result's."""
    normal = EYE_CAMERA_TO_WORLD.T @ gaze_normal  # the pupil faces the eye camera
    radius = PUPIL_DIAMETER_MM / 2
    centre = SPHERE_IN_EYE_CAMERA + EYE_RADIUS_MM * normal
    major = 2 * EYE_FOCAL_PX * radius / centre[2]
    minor = major * abs(normal @ centre) / np.linalg.norm(centre)  # foreshortened along the tilt
    location = _eye_pixel(centre)
    sphere_px = float(2 * EYE_FOCAL_PX * EYE_RADIUS_MM / SPHERE_IN_EYE_CAMERA[2])
    phi, theta = np.arctan2(normal[2], normal[0]), np.arccos(np.clip(normal[1], -1.0, 1.0))  # pye3d's cart2sph
    plausible = abs(np.degrees(phi) + 90.0) <= 80 and abs(np.degrees(theta) - 90.0) <= 80
    ellipse = {
        "center": _floats(location),
        "axes": [float(minor), float(major)],
        "angle": float(np.degrees(np.arctan2(normal[1], normal[0]))),  # of the minor axis, the tilt's direction
    }
    return {
        "id": eye_id,
        "topic": f"pupil.{eye_id}.3d",
        "method": PUPIL_METHOD,
        "norm_pos": [float(location[0] / EYE_IMAGE_PX), float(1.0 - location[1] / EYE_IMAGE_PX)],
        "diameter": float(major),
        "confidence": confidence,
        "timestamp": timestamp_s,
        "sphere": {"center": _floats(SPHERE_IN_EYE_CAMERA), "radius": EYE_RADIUS_MM},
        "projected_sphere": {
            "center": _floats(_eye_pixel(SPHERE_IN_EYE_CAMERA)),
            "axes": [sphere_px, sphere_px],
            "angle": 0.0,
        },
        "circle_3d": {"center": _floats(centre), "normal": _floats(normal), "radius": radius},
        "diameter_3d": PUPIL_DIAMETER_MM,
        "ellipse": ellipse,
        "location": ellipse["center"],
        "model_confidence": 1.0 if plausible else 0.1,
        "theta": float(theta),
        "phi": float(phi),
    }


def gaze_datum(sample: FeedSample, timestamp_s: float) -> dict:
    """A feed sample (our head frame) as a binocular Pupil gaze datum (section 3.2) with its pupil datums in
    base_data, as Capture 3.5's Gazer3D maps them; untracked: confidence 0."""
    centre = mean_direction(sample.left, sample.right) if sample.valid else None
    tracked = centre is not None
    if not tracked:
        left = right = centre = np.array([0.0, 0.0, -1.0])
    else:
        left, right = sample.left, sample.right
    c = opencv_head(centre)
    u, v = 0.5 + 0.5 * c[0] / c[2], 0.5 - 0.5 * c[1] / c[2]  # a 90-degree pinhole; norm_pos origin is bottom-left
    normals = (opencv_head(right), opencv_head(left))  # eye 0 is the right eye
    confidence = CONFIDENCE if tracked else 0.0
    distance_mm = sample.depth_m * 1000.0 if tracked and sample.depth_m else GAZE_DISTANCE_MM
    return {
        "eye_centers_3d": {"0": [IPD_MM / 2, 0.0, 0.0], "1": [-IPD_MM / 2, 0.0, 0.0]},
        "gaze_normals_3d": {"0": _floats(normals[0]), "1": _floats(normals[1])},
        "gaze_point_3d": _floats(c * distance_mm),
        "norm_pos": _floats((u, v)),
        "topic": GAZE_TOPIC,
        "confidence": confidence,
        "timestamp": timestamp_s,
        "base_data": [pupil_datum(eye, normals[eye], confidence, timestamp_s) for eye in (0, 1)],
    }


class PupilEmulator(NetworkEmulator):
    """Pupil Remote on host:port (0 = any free port; see `address`) and its backbone."""

    name = "pupil"
    emulates = (Emulated("pupil", rate_hz=RATE_HZ, port=DEFAULT_PORT, latency_ms=0.0),)  # Pupil Remote's port

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        feed: GazeFeed | None = None,
        rate_hz: float = RATE_HZ,
        clock: Clock = MONOTONIC,
    ):
        """feed: the gaze source (default: synthetic gaze at rate_hz; a given feed brings its own rate)."""
        super().__init__(host, port, clock)
        self.feed = feed if feed is not None else GazeFeed(rate_hz, clock=clock)
        self.sub_port: int | None = None
        self.pub_port: int | None = None
        self.malformed = 0

    def pupil_time(self, t_ns: int | None = None) -> float:
        """Pupil time (s) of a host time (default: now)."""
        return ((self.clock.now_ns() if t_ns is None else t_ns) - self.epoch_ns) / 1e9

    def _socket(self, kind: int, port: int = 0) -> tuple[zmq.Socket, int]:
        """A socket of `kind` bound to host:port (0: a free port), and that port."""
        sock = zmq.Context.instance().socket(kind)
        sock.setsockopt(zmq.LINGER, 0)
        sock.setsockopt(zmq.MAXMSGSIZE, MAX_ZMQ_MESSAGE)
        if port:
            sock.bind(f"tcp://{self.host}:{port}")
            return sock, port
        return sock, sock.bind_to_random_port(f"tcp://{self.host}")

    def _bind(self) -> None:
        self._remote, port = self._socket(zmq.REP, self.port)
        self._backbone, self.sub_port = self._socket(zmq.PUB)
        self._inbox, self.pub_port = self._socket(zmq.SUB)
        self._inbox.setsockopt(zmq.SUBSCRIBE, b"")
        self._address = (self.host, port)
        self._poller = zmq.Poller()
        self._poller.register(self._remote, zmq.POLLIN)
        self._poller.register(self._inbox, zmq.POLLIN)
        self._samples = self.feed.samples()
        self._sample = next(self._samples)

    def _release(self) -> None:
        for sock in (self._remote, self._backbone, self._inbox):
            sock.close(linger=0)

    def _tick(self, now_ns: int) -> int:
        while self._sample.due_ns <= now_ns:
            datum = gaze_datum(self._sample, self.pupil_time(self._sample.capture_ns))
            for pupil in datum["base_data"]:  # the eye processes publish before the gaze mapper
                self._backbone.send_multipart([pupil["topic"].encode(), msgspec.msgpack.encode(pupil)])
            self._backbone.send_multipart([GAZE_TOPIC.encode(), msgspec.msgpack.encode(datum)])
            self._log_sent(self._sample.capture_ns - self.epoch_ns)
            self._sample = next(self._samples)
        return self._sample.due_ns

    def _poll(self, timeout_s: float) -> None:
        ready = dict(self._poller.poll(int(timeout_s * 1000)))  # whole milliseconds, zmq_poll's resolution
        if not ready:
            time.sleep(timeout_s % 0.001)  # and the rest, so that samples leave when they are due
            return
        if self._remote in ready:
            self._remote.send_string(self._reply(self._remote.recv_multipart()))
        if self._inbox in ready:
            self._relay()

    def _relay(self) -> None:
        for _ in range(MAX_RELAY):
            try:
                self._backbone.send_multipart(self._inbox.recv_multipart(zmq.NOBLOCK))
            except zmq.Again:
                return

    def _reply(self, frames: list[bytes]) -> str:
        """Pupil Remote's answer to one request (section 3.1)."""
        if len(frames) > 1:
            return self._forward(frames)
        try:
            msg = frames[0].decode("utf-8")
        except UnicodeDecodeError:
            self.malformed += 1
            return UNKNOWN
        if msg in ("SUB_PORT", "PUB_PORT"):
            return str(self.sub_port if msg == "SUB_PORT" else self.pub_port)
        if msg in ("C", "c"):
            self._notify("calibration.should_start" if msg == "C" else "calibration.should_stop")
            return "OK"
        match msg[:1]:  # Pupil Remote matches these on the first character only
            case "R":
                self._notify("recording.should_start", session_name=msg[2:])
                return "OK"
            case "r":
                self._notify("recording.should_stop")
                return "OK"
            case "T":
                return self._rebase(msg[2:])
            case "t":
                return repr(self.pupil_time())
            case "v":
                return VERSION
        return UNKNOWN

    def _rebase(self, text: str) -> str:
        try:
            target = float(text)
        except ValueError:
            target = math.nan
        if not math.isfinite(target):
            return f"'{text}' cannot be converted to float."
        self.epoch_ns = self.clock.now_ns() - round(target * 1e9)
        return "Timesync successful."

    def _forward(self, frames: list[bytes]) -> str:
        try:
            frames[0].decode("utf-8")
            if not isinstance(msgspec.msgpack.decode(frames[1]), dict):
                raise msgspec.DecodeError("payload is not a map")
        except (UnicodeDecodeError, msgspec.DecodeError, RecursionError):
            self.malformed += 1
            return UNKNOWN
        self._backbone.send_multipart(frames)
        return "Message forwarded."

    def _notify(self, subject: str, **fields) -> None:
        payload = msgspec.msgpack.encode({"subject": subject, **fields})
        self._backbone.send_multipart([f"notify.{subject}".encode(), payload])
