"""smi://HOST:PORT: an SMI iView X eye tracker (or drivers.emulators.smi_server) over UDP (docs/protocols.md, SMI).

open() pings the tracker (ET_PNG, answered within 3 s or DeviceLost), asks its sample rate (ET_SRT),
sets the sample format "%TU %ET %SX %SY" (ET_FRM, section 1.3) and starts streaming (ET_STR, section
1.2). Each ET_SPL line becomes one Gaze: the screen pixels of each eye become unit directions in the
head frame through that eye's camera of the HMD profile; an eye at (0, 0) has no data (section 1.5),
so a sample with no tracked eye is invalid and a monocular one (eye type l or r) carries that eye
only; C is the normalised mean of L and R when both are tracked. t_dev is the tracker's %TU (or %TS)
in nanoseconds, mapped to host capture time by the clock sync. A tracker that ignores ET_FRM may
stream one of the RED capture formats of section 7 (items 1 and 3); a line that does not match the
driver's own format is tried against those, and counted as malformed when none fits. Waits are in
real time (this is a network device); receive times are read from the driver's clock.
"""

from __future__ import annotations

import contextlib
import ipaddress
import socket
import time

import numpy as np

from hmdrt.bus.messages import Gaze
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DeviceLost, Driver, DriverError, DriverUrl, Sample
from hmdrt.drivers.protocols.smi import (
    GAZE_FORMAT,
    MAX_LINE_BYTES,
    RED_FORMATS,
    SampleFormat,
    SmiError,
    SplSample,
    command,
    decode,
    encode,
    int_args,
    parse_line,
)
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.spatial import Pose, mean_direction

DEFAULT_PORT = 4444  # the tracker's command port in iView X's defaults (section 1.1)
HANDSHAKE_S = 3.0  # the SDK's connect timeout (section 1.1)
RESEND_S = 0.5  # a lost ping or rate query is sent again after this long
SILENCE_S = 1.0  # a streaming tracker that says nothing for this long (or 3 sample periods) is lost
MAX_PIXELS = 2**31  # screen coordinate range (section 1.3)
MAX_T_DEV_NS = 2**62  # the bus's time range
_EYES = {"l": ("L",), "r": ("R",), "b": ("L", "R")}


class SmiDriver(Driver):
    scheme = "smi"
    grammar = (
        "smi://HOST:PORT?listen=PORT&rate=HZ&profile=NAME&name=DEVICE (defaults port 4444; listen 5555, the "
        "client port iView X sends to, 0 = a free port for trackers that answer the sender; rate 250; profile dk2)"
    )
    options = {
        "listen": (int, 5555, 0, 65535),
        "rate": (int, 250, 1, 2000),
        "profile": (str, "dk2", None, None),
    }

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        super().__init__(url, clock)
        display = get_profile(self.opt["profile"])
        self._cameras = {
            "L": EyeCamera.for_eye(display, Pose(), "left"),
            "R": EyeCamera.for_eye(display, Pose(), "right"),
        }
        for camera in self._cameras.values():
            camera.directions(np.zeros((1, 2)))  # load the compiled kernel now, not while the first samples queue up
        self._formats = tuple(SampleFormat.parse(text) for text in (GAZE_FORMAT, *RED_FORMATS))
        self._host, self._port = self.url.host or "127.0.0.1", self.url.port or DEFAULT_PORT
        self._tracker: tuple[str, int] | None = None
        self._sock: socket.socket | None = None
        self._silence_ns = int(SILENCE_S * 1e9)
        self._heard_ns = 0  # real time of the last well-formed line from the tracker
        self._seq = 0

    @property
    def local_address(self) -> tuple[str, int]:
        """The (host, port) this driver receives on, once open."""
        if self._sock is None:
            raise DriverError("smi:// is not open")
        host, port = self._sock.getsockname()[:2]
        return host, port

    def open(self) -> None:
        self.close()
        try:
            ip = socket.gethostbyname(self._host)
        except OSError as exc:
            raise DriverError(f"smi:// cannot resolve tracker host {self._host!r}: {exc}") from None
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(("127.0.0.1" if ipaddress.ip_address(ip).is_loopback else "0.0.0.0", self.opt["listen"]))
        except OSError as exc:
            sock.close()
            raise DriverError(f"smi:// cannot listen on port {self.opt['listen']}: {exc.strerror}") from None
        self._sock, self._tracker = sock, (ip, self._port)
        try:
            self._ask("ET_PNG")
            rate = self._stream_rate(self._ask("ET_SRT"))
            self._send(command("ET_FRM", GAZE_FORMAT))
            self._send(command("ET_STR", rate))
        except DriverError:
            self.close()
            raise
        self._silence_ns = int(max(SILENCE_S, 3.0 / rate) * 1e9)
        self._heard_ns = time.monotonic_ns()
        self.state = "connected"

    def read(self, timeout_s: float) -> list[Sample]:
        if self._sock is None:
            raise DriverError("smi:// read before open")
        deadline = time.monotonic_ns() + int(timeout_s * 1e9)
        batch: list[tuple[SplSample, int]] = []
        while True:
            # wait for the first datagram, then take only what is already queued
            until = time.monotonic_ns() if batch else min(deadline, self._heard_ns + self._silence_ns)
            received = self._receive(until)
            if received is None:
                if time.monotonic_ns() - self._heard_ns >= self._silence_ns:
                    raise DeviceLost(
                        f"smi:// tracker at {self._host}:{self._port} sent nothing for {self._silence_ns / 1e9:g} s"
                    )
                if batch or time.monotonic_ns() >= deadline:
                    return self.count(self._gazes(batch))
                continue
            text, t_recv = received
            sample = self._sample(text)
            if sample is not None:
                batch.append((sample, t_recv))

    def close(self) -> None:
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.sendto(encode("ET_EST"), self._tracker)
            self._sock.close()
            self._sock = None
        self.state = "closed"

    def _send(self, text: str) -> None:
        try:
            self._sock.sendto(encode(text), self._tracker)
        except OSError as exc:
            raise DeviceLost(f"smi:// cannot send to {self._host}:{self._port}: {exc.strerror}") from None

    def _receive(self, until_ns: int) -> tuple[str, int] | None:
        """The next datagram from the tracker as text, with its receive time on the driver's clock; None
        once real time reaches until_ns. Oversized, foreign and undecodable datagrams are counted as malformed."""
        while True:
            self._sock.settimeout(max(until_ns - time.monotonic_ns(), 0) / 1e9)
            try:
                data, addr = self._sock.recvfrom(MAX_LINE_BYTES + 1)
            except (TimeoutError, BlockingIOError):
                return None
            except ConnectionError:  # an ICMP error for an earlier send, reported here on some systems
                continue
            t_recv = self.clock.now_ns()
            try:
                if len(data) > MAX_LINE_BYTES:
                    raise SmiError(f"datagram of {len(data)} bytes exceeds {MAX_LINE_BYTES}")
                if addr[0] != self._tracker[0]:
                    raise SmiError(f"datagram from {addr[0]}, not the tracker")
                return decode(data), t_recv
            except SmiError:
                self.counters.malformed += 1

    def _ask(self, mnemonic: str) -> tuple[str, ...]:
        """Send a query and return the arguments of the tracker's reply of the same mnemonic."""
        deadline = time.monotonic_ns() + int(HANDSHAKE_S * 1e9)
        while time.monotonic_ns() < deadline:
            self._send(mnemonic)
            resend = min(deadline, time.monotonic_ns() + int(RESEND_S * 1e9))
            while (received := self._receive(resend)) is not None:
                try:
                    reply, args = parse_line(received[0])
                except SmiError:
                    self.counters.malformed += 1
                    continue
                if reply == mnemonic:
                    return args
        raise DeviceLost(f"smi:// no {mnemonic} reply from {self._host}:{self._port} within {HANDSHAKE_S:g} s")

    def _stream_rate(self, reply: tuple[str, ...]) -> int:
        """The rate to ask for, checked against the tracker's (the arguments of its ET_SRT reply)."""
        try:
            (tracker_rate,) = int_args(reply, 1, 100_000)
        except SmiError as exc:
            raise DriverError(f"smi:// tracker at {self._host}:{self._port} sent a bad ET_SRT reply: {exc}") from None
        rate = self.opt["rate"]
        if rate > tracker_rate:
            raise DriverError(
                f"smi:// rate={rate} exceeds the tracker's {tracker_rate} Hz; ask for {tracker_rate} or less"
            )
        return rate

    def _sample(self, text: str) -> SplSample | None:
        """The fields of an ET_SPL line; other well-formed lines (replies, fixation events) give None."""
        try:
            mnemonic, _ = parse_line(text)  # the parsed mnemonic decides, whatever whitespace came before it
            sample = self._parse(text) if mnemonic == "ET_SPL" else None
        except SmiError:
            self.counters.malformed += 1
            return None
        self._heard_ns = time.monotonic_ns()
        return sample

    def _parse(self, text: str) -> SplSample:
        """The line in the driver's own format, else in the first RED capture format it matches, with its
        time and screen positions in range (every one of these formats has %ET, %SX, %SY and a time)."""
        for fmt in self._formats:
            with contextlib.suppress(SmiError):
                sample = fmt.parse_line(text)
                break
        else:
            raise SmiError(f"ET_SPL line matches no known format: {text[:120]!r}")
        if sample.timestamp_us * 1000 > MAX_T_DEV_NS:
            raise SmiError(f"tracker time {sample.timestamp_us} us is out of range")
        if max(map(abs, sample.values["SX"] + sample.values["SY"])) > MAX_PIXELS:
            raise SmiError(f"screen position out of range: {text[:120]!r}")
        return sample

    def _gazes(self, batch: list[tuple[SplSample, int]]) -> list[Gaze]:
        """Gaze of parsed samples, oldest first; each eye's pixels go through its camera in one call."""
        pixels: dict[str, dict[int, tuple[float, float]]] = {"L": {}, "R": {}}
        for i, (sample, _) in enumerate(batch):
            for j, key in enumerate(_EYES[sample.eye]):
                xy = (sample.values["SX"][j], sample.values["SY"][j])
                if xy != (0.0, 0.0):  # (0, 0): no data for this eye (docs/protocols.md, SMI)
                    pixels[key][i] = xy
        directions = {
            key: dict(zip(found, self._cameras[key].directions(np.array(list(found.values()))), strict=True))
            for key, found in pixels.items()
            if found
        }
        out = []
        for i, (sample, t_recv) in enumerate(batch):
            eyes = {key: rows[i].astype(np.float64) for key, rows in directions.items() if i in rows}
            centre = mean_direction(eyes["L"], eyes["R"]) if len(eyes) == 2 else None
            t_dev = sample.timestamp_us * 1000
            out.append(
                Gaze(
                    seq=self._seq,
                    t_host=self.sync.add(t_dev, t_recv),
                    t_dev=t_dev,
                    valid=bool(eyes),
                    C=None if centre is None else tuple(map(float, centre)),
                    L=tuple(map(float, eyes["L"])) if "L" in eyes else None,
                    R=tuple(map(float, eyes["R"])) if "R" in eyes else None,
                )
            )
            self._seq += 1
        return out
