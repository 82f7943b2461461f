"""An SMI iView X tracker on UDP, speaking the remote command interface of docs/protocols.md, SMI.

Gaze comes from a GazeFeed (a trace or the seeded synthetic generator) and is reported as an SMI HMD
tracker reports its point of regard: in the pixels of each eye's display of an HMD profile, the left
gaze through the left eye camera and the right through the right; invalid samples read (0, 0)
(section 1.5). One daemon thread waits on the command socket and on the next sample's due time
together (select), so commands are answered while streaming and stop() is prompt. Malformed or
unknown commands are counted in `malformed`, datagrams over MAX_LINE_BYTES in `oversized`.

Where section 1 is silent, the emulator chooses:
- ET_SPL lines use "%TU %ET %SX %SY" until a client sends ET_FRM; the eye type is always b.
- The tracker clock counts from the emulator's start: %TU in microseconds, %TS in milliseconds.
- %SX %SY are rounded to 0.01 px; the other per-eye specifiers come from a fixed eye model (_eye_values).
- Replies: ET_PNG, ET_SRT <rate>, ET_CSZ <w> <h> (echoed: the tracker announces a changed area), ET_BRK
  (echoed to confirm the abort) and the recording commands (echoed; nothing is recorded). ET_FRM,
  ET_STR, ET_EST, ET_DEF, ET_PNT, ET_CPA, ET_LEV, ET_FIX and ET_EFX get no reply.
- Calibration with n points (ET_CAL n) is answered as iView X answers it: ET_CAL n (the number of points,
  which clients size their list of points from), ET_CSZ <w> <h>, ET_PNT 1..n, then ET_CHG 1. The points
  are the first n of: centre, corners, edge midpoints, inner points (at 10, 30, 50, 70 and 90 % of the
  area), except points a client set with ET_PNT (until ET_DEF).
- ET_VLS reports per eye, at the area's centre, the feed's RMS error in degrees: along x the accuracy
  offset with the precision noise, along y the noise, and both combined.
- ET_FIX [dur disp] runs dispersion-threshold fixation detection per eye (smi_fixations; defaults 75 ms, 45 px, as
  PyViewX); lost tracking ends a fixation; events go to the client that sent ET_FIX.
"""

from __future__ import annotations

import math
import select
import socket
from collections.abc import Callable

import numpy as np

from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DriverError
from hmdrt.drivers.emulators.base import Address, Emulated, NetworkEmulator
from hmdrt.drivers.emulators.feed import FeedSample, GazeFeed
from hmdrt.drivers.emulators.smi_fixations import FixationDetector
from hmdrt.drivers.protocols.smi import (
    GAZE_FORMAT,
    MAX_LINE_BYTES,
    PER_EYE,
    SampleFormat,
    SmiError,
    SplSample,
    Validation,
    command,
    decode,
    encode,
    int_args,
    parse_line,
)
from hmdrt.drivers.smi import DEFAULT_PORT
from hmdrt.errors import ConfigError
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.spatial import Pose

RATE_HZ = 250  # the emulated tracker's default sample rate
MAX_AREA_PX = 16384
MAX_FIXATION_MS = 1000  # bounds the candidate window a fixation detector scans per sample
CALIBRATION_SIZES = (2, 5, 9, 13)
_LAYOUT = (  # calibration points as fractions of the area, in the order they are shown
    ((0.5, 0.5),)  # centre
    + ((0.1, 0.1), (0.9, 0.1), (0.1, 0.9), (0.9, 0.9))  # corners
    + ((0.5, 0.1), (0.9, 0.5), (0.5, 0.9), (0.1, 0.5))  # edge midpoints
    + ((0.3, 0.3), (0.7, 0.3), (0.3, 0.7), (0.7, 0.7))  # inner points
)
Handler = Callable[[tuple[str, ...], Address], None]


def _no_args(args: tuple[str, ...]) -> None:
    if args:
        raise SmiError(f"expected no arguments, got {' '.join(args)!r}")


def _eye_values(camera: EyeCamera, gaze: np.ndarray, pixel: np.ndarray) -> dict[str, float]:
    """Per-eye values of a tracked eye: its point of regard, then a fixed eye model (pupil 12 px across,
    its centre moving with the gaze in a 320 x 240 eye image, the corneal reflex still, the eye IPD / 2
    to the side of a camera 30 mm in front of it)."""
    return {
        "SX": round(float(pixel[0]), 2),
        "SY": round(float(pixel[1]), 2),
        "DX": 12.0,
        "DY": 12.0,
        "PX": round(160.0 + 100.0 * float(gaze[0]), 3),
        "PY": round(120.0 - 100.0 * float(gaze[1]), 3),
        "CX": 160.0,
        "CY": 140.0,
        "EX": round(float(camera.position[0]) * 1000.0, 3),
        "EY": 0.0,
        "EZ": 30.0,
    }


class SmiEmulator(NetworkEmulator):
    """An SMI tracker at host:port (port 0: a free one; see `address` after start())."""

    name = "smi"
    driver_options = "?listen=0"  # the emulator answers the sender, so the driver may take any free port
    emulates = (Emulated("smi", rate_hz=RATE_HZ, port=DEFAULT_PORT, latency_ms=0.0),)

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = 0,
        feed: GazeFeed | None = None,
        rate_hz: int = RATE_HZ,
        profile: str = "dk2",
        clock: Clock = MONOTONIC,
    ):
        if int(rate_hz) != rate_hz or not 1 <= rate_hz <= 2000:
            raise ConfigError(f"SMI tracker rate must be a whole number of Hz within 1..2000, got {rate_hz}")
        if feed is not None and feed.rate_hz != rate_hz:
            raise ConfigError(f"the gaze feed runs at {feed.rate_hz} Hz but the tracker at {rate_hz} Hz")
        super().__init__(host, port, clock)
        self.rate_hz = int(rate_hz)
        self.feed = feed if feed is not None else GazeFeed(rate_hz, clock=clock)
        display = get_profile(profile)
        self._cameras = (EyeCamera.for_eye(display, Pose(), "left"), EyeCamera.for_eye(display, Pose(), "right"))
        self._display = (display.width, display.height)
        self._period_ns = round(1e9 / self.rate_hz)
        self.malformed = 0  # unknown commands and commands with bad arguments
        self.oversized = 0  # datagrams over MAX_LINE_BYTES
        self.send_errors = 0
        self._sock: socket.socket | None = None
        self._handlers: dict[str, Handler] = {
            "ET_PNG": self._ping,
            "ET_SRT": self._sample_rate,
            "ET_FRM": self._set_format,
            "ET_STR": self._start_stream,
            "ET_EST": self._end_stream,
            "ET_CAL": self._calibrate,
            "ET_ACC": self._accept,
            "ET_BRK": self._abort,
            "ET_CSZ": self._set_area,
            "ET_PNT": self._set_point,
            "ET_DEF": self._default_points,
            "ET_CPA": self._accept_ints(0, 3, (1, 2)),
            "ET_LEV": self._accept_ints(0, 3, (1,)),
            "ET_VLS": self._validate,
            "ET_FIX": self._start_fixations,
            "ET_EFX": self._end_fixations,
            **{m: self._acknowledge(m, (0,)) for m in ("ET_REC", "ET_STP", "ET_CLR")},
            **{m: self._acknowledge(m, None) for m in ("ET_PSE", "ET_CNT")},
            "ET_SAV": self._acknowledge("ET_SAV", (1,)),
        }
        self._reset()

    def _reset(self) -> None:
        """The state a tracker starts with: default format and area, nothing running."""
        self._format = SampleFormat.parse(GAZE_FORMAT)
        self._stream_to: Address | None = None
        self._stream_period_ns = self._period_ns
        self._next_send_ns = 0
        self._area = self._display
        self._custom_points: dict[int, tuple[int, int]] = {}
        self._calibration: tuple[Address, list[tuple[int, int]]] | None = None
        self._point = 0
        self._detectors: tuple[FixationDetector, FixationDetector] | None = None
        self._events_to: Address | None = None

    @property
    def streaming(self) -> bool:
        return self._stream_to is not None

    def _bind(self) -> None:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, self.port))
        except OSError as exc:
            sock.close()
            raise DriverError(f"SMI emulator cannot listen on {self.host}:{self.port}: {exc.strerror}") from None
        sock.setblocking(False)
        self._sock = sock
        self._address = sock.getsockname()[:2]
        self._reset()
        self._samples = self.feed.samples()
        self._pending = next(self._samples)
        self.epoch_ns = self._pending.capture_ns  # the tracker clock counts from the first sample

    def _release(self) -> None:
        self._sock.close()
        self._sock = None

    def _tick(self, now_ns: int) -> int:
        while self._pending.due_ns <= now_ns:
            self._emit(self._pending, (self._pending.capture_ns - self.epoch_ns) // 1000)
            self._pending = next(self._samples)
        return self._pending.due_ns

    def _poll(self, timeout_s: float) -> None:
        readable, _, _ = select.select([self._sock], [], [], timeout_s)
        if readable:
            self._receive()

    def _receive(self) -> None:
        """Handle every queued command; bad ones are counted and ignored."""
        while True:
            try:
                data, addr = self._sock.recvfrom(MAX_LINE_BYTES + 1)
            except BlockingIOError:
                return
            except ConnectionError:  # an ICMP error for an earlier send, reported here on some systems
                continue
            if len(data) > MAX_LINE_BYTES:
                self.oversized += 1
                continue
            try:
                mnemonic, args = parse_line(decode(data))
                if mnemonic not in self._handlers:
                    raise SmiError(f"unknown command {mnemonic}")
                self._handlers[mnemonic](args, addr)
            except SmiError:
                self.malformed += 1

    def _send(self, text: str, addr: Address) -> None:
        try:
            self._sock.sendto(encode(text), addr)
        except OSError:
            self.send_errors += 1

    def _emit(self, sample: FeedSample, t_us: int) -> None:
        """Stream one tracker sample and feed the fixation detectors, when a client asked for either."""
        if self._stream_to is None and self._detectors is None:
            return
        pixels = [
            self._pixel(cam, gaze) if sample.valid else None
            for cam, gaze in zip(self._cameras, (sample.left, sample.right), strict=True)
        ]
        if self._detectors is not None:
            for detector, pixel in zip(self._detectors, pixels, strict=True):
                event = detector.add(t_us, None if pixel is None else (float(pixel[0]), float(pixel[1])))
                if event is not None:
                    self._send(event.line(), self._events_to)
        if self._stream_to is not None and sample.capture_ns + self._period_ns // 2 >= self._next_send_ns:
            self._next_send_ns = max(self._next_send_ns, sample.capture_ns) + self._stream_period_ns
            eyes = [
                dict.fromkeys(PER_EYE, 0.0) if pixel is None else _eye_values(cam, gaze, pixel)
                for cam, gaze, pixel in zip(self._cameras, (sample.left, sample.right), pixels, strict=True)
            ]
            values = {name: (eyes[0][name], eyes[1][name]) for name in PER_EYE}
            values.update(TU=t_us, TS=t_us // 1000, SC=sample.index)
            self._log_sent(t_us * 1000)  # before the send: a client may read it (and stop) before send returns
            self._send(self._format.format_line(SplSample("b", values)), self._stream_to)

    @staticmethod
    def _pixel(camera: EyeCamera, gaze: np.ndarray) -> np.ndarray | None:
        """Where the gaze meets the eye's display, or None when it points behind it (lost tracking)."""
        xy, depth = camera.project((camera.position + gaze)[None])
        return xy[0] if depth[0] > 0 and np.isfinite(xy).all() else None

    def _ping(self, args: tuple[str, ...], addr: Address) -> None:
        _no_args(args)
        self._send("ET_PNG", addr)

    def _sample_rate(self, args: tuple[str, ...], addr: Address) -> None:
        _no_args(args)
        self._send(command("ET_SRT", self.rate_hz), addr)

    def _set_format(self, args: tuple[str, ...], addr: Address) -> None:
        if len(args) != 1:
            raise SmiError('ET_FRM takes one quoted format, e.g. ET_FRM "%TU %ET %SX %SY"')
        self._format = SampleFormat.parse(args[0])

    def _start_stream(self, args: tuple[str, ...], addr: Address) -> None:
        rate = int_args(args, 1, self.rate_hz, (0, 1)) or [self.rate_hz]
        # samples captured from now on: a backlog the server thread may have is not streamed
        self._stream_to, self._stream_period_ns = addr, round(1e9 / rate[0])
        self._next_send_ns = self.clock.now_ns()

    def _end_stream(self, args: tuple[str, ...], addr: Address) -> None:
        _no_args(args)
        self._stream_to = None

    def _calibrate(self, args: tuple[str, ...], addr: Address) -> None:
        n, *eye = int_args(args, 1, 13, (1, 2))  # eye 1 right, 2 left: both eyes calibrate together here
        if n not in CALIBRATION_SIZES or eye not in ([], [1], [2]):
            raise SmiError(f"ET_CAL takes n in {CALIBRATION_SIZES} and an optional eye 1 or 2, got {args}")
        w, h = self._area
        points = [
            self._custom_points.get(i + 1, (round(fx * w), round(fy * h))) for i, (fx, fy) in enumerate(_LAYOUT[:n])
        ]
        self._calibration, self._point = (addr, points), 1
        self._send(command("ET_CAL", n), addr)  # first: clients size their list of points from it (section 1.7)
        self._send(command("ET_CSZ", w, h), addr)
        for i, (x, y) in enumerate(points, start=1):
            self._send(command("ET_PNT", i, x, y), addr)
        self._send(command("ET_CHG", 1), addr)

    def _accept(self, args: tuple[str, ...], addr: Address) -> None:
        _no_args(args)
        if self._calibration is None:
            raise SmiError("ET_ACC outside a calibration")
        client, points = self._calibration
        if self._point < len(points):
            self._point += 1
            self._send(command("ET_CHG", self._point), client)
        else:
            self._calibration = None
            self._send("ET_FIN", client)

    def _abort(self, args: tuple[str, ...], addr: Address) -> None:
        _no_args(args)
        self._calibration = None
        self._send("ET_BRK", addr)

    def _set_area(self, args: tuple[str, ...], addr: Address) -> None:
        self._area = tuple(int_args(args, 1, MAX_AREA_PX, (2,)))
        self._send(command("ET_CSZ", *self._area), addr)

    def _set_point(self, args: tuple[str, ...], addr: Address) -> None:
        i, x, y = int_args(args, 0, MAX_AREA_PX, (3,))
        if not 1 <= i <= len(_LAYOUT):
            raise SmiError(f"calibration point {i} is outside 1..{len(_LAYOUT)}")
        self._custom_points[i] = (x, y)

    def _default_points(self, args: tuple[str, ...], addr: Address) -> None:
        _no_args(args)
        self._custom_points.clear()

    def _validate(self, args: tuple[str, ...], addr: Address) -> None:
        _no_args(args)
        noise, offset = self.feed.noise_deg, self.feed.offset_deg
        x_deg = round(math.hypot(offset, noise), 3)
        y_deg = round(noise, 3)
        w, h = self._area
        for eye in ("l", "r"):
            self._send(Validation(eye, w // 2, h // 2, round(math.hypot(x_deg, y_deg), 3), x_deg, y_deg).line(), addr)

    def _start_fixations(self, args: tuple[str, ...], addr: Address) -> None:
        duration_ms, dispersion_px = int_args(args, 1, 10_000, (0, 2)) or (75, 45)
        if duration_ms > MAX_FIXATION_MS:
            raise SmiError(f"ET_FIX minimum duration {duration_ms} ms exceeds {MAX_FIXATION_MS} ms")
        self._detectors = (
            FixationDetector("l", duration_ms, dispersion_px),
            FixationDetector("r", duration_ms, dispersion_px),
        )
        self._events_to = addr

    def _end_fixations(self, args: tuple[str, ...], addr: Address) -> None:
        _no_args(args)
        self._detectors = None

    def _acknowledge(self, mnemonic: str, counts: tuple[int, ...] | None) -> Handler:
        """A recording command: checks how many arguments it has (any when counts is None) and echoes it."""

        def handler(args: tuple[str, ...], addr: Address) -> None:
            if counts is not None and len(args) not in counts:
                raise SmiError(f"{mnemonic} takes {' or '.join(map(str, counts))} arguments, got {len(args)}")
            self._send(mnemonic, addr)

        return handler

    @staticmethod
    def _accept_ints(lo: int, hi: int, counts: tuple[int, ...]) -> Handler:
        """A setting the emulator accepts without acting on it (ET_CPA, ET_LEV): its arguments are checked."""

        def handler(args: tuple[str, ...], addr: Address) -> None:
            int_args(args, lo, hi, counts)

        return handler
