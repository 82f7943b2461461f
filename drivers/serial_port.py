"""serial://: Razor AHRS and HATIRE head trackers over a serial port (docs/protocols.md, Razor and HATIRE).

    serial:///dev/ttyUSB0?protocol=razor          a device path (three slashes: the URL path is the device)
    serial://?port=loop://&protocol=hatire        any pyserial URL (loop://, socket://, spy://...) in port=

The port is opened with pyserial's serial_for_url at 57600 baud for Razor and 115200 for HATIRE unless
baud= says otherwise. On open the driver starts the stream (Razor `#ot#o1`: text frames, streaming on;
HATIRE `S`). Bytes are framed incrementally (drivers.protocols.razor / hatire); bytes that belong to no
valid frame are counted in counters.malformed (in bytes). Angle frames become Pose samples in the head
frame (razor.ypr_to_quat, both protocols; HATIRE's axes are an assumption documented in its module),
position (0, 0, 0). Neither device sends a timestamp, so t_dev is None and t_host is the time the
bytes were read. HATIRE's frame counter (0..999, wrapping) gives lost frames in counters.dropped. A read
or write error, or the device going away, raises DeviceLost.
"""

from __future__ import annotations

import math
from urllib.parse import urlsplit

import serial

from drivers.base import DeviceLost, Driver, DriverUrl, Sample, SequenceGaps
from drivers.protocols import hatire, razor
from hmdrt.bus.messages import Pose
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.errors import ConfigError

MAX_CHUNK = 4096
POLL_S = 0.01  # pyserial read timeout; read(timeout_s) waits in steps of this

PROTOCOLS = {
    "razor": (razor.BAUD, b"#ot#o1", razor.RazorFramer, razor.Ypr),
    "hatire": (hatire.BAUD, hatire.START, hatire.HatireFramer, hatire.HatireFrame),
}


class SerialDriver(Driver):
    scheme = "serial"
    grammar = (
        "serial:///dev/ttyUSB0?protocol=razor|hatire&baud=N&name=DEVICE "
        "or serial://?port=PYSERIAL_URL&protocol=razor|hatire&baud=N (e.g. port=loop://); "
        "protocol is required; baud defaults to 57600 for razor, 115200 for hatire"
    )
    options = {
        "protocol": (str, "", None, None),
        "baud": (int, None, 50, 4_000_000),
        "port": (str, "", None, None),
    }

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        super().__init__(url, clock)
        protocol = self.opt["protocol"]
        if protocol not in PROTOCOLS:
            raise ConfigError(f"serial:// needs protocol=razor or protocol=hatire, got {protocol!r}; {self.grammar}")
        if urlsplit(self.url.text).netloc:
            raise ConfigError(f"serial:// takes the device as the URL path (serial:///dev/ttyUSB0); {self.grammar}")
        if bool(self.url.path) == bool(self.opt["port"]):
            raise ConfigError(f"serial:// needs a device path or port=, not both or neither; {self.grammar}")
        default_baud, self._start_command, self._framer_class, self._angles = PROTOCOLS[protocol]
        self.target = self.url.path or self.opt["port"]
        self.baud = self.opt["baud"] or default_baud
        self.port: serial.SerialBase | None = None  # the open pyserial port (with loop://, tests write into it)

    def open(self) -> None:
        self.close()
        try:
            self.port = serial.serial_for_url(self.target, baudrate=self.baud, timeout=POLL_S)
        except ValueError as exc:
            raise ConfigError(f"serial:// cannot use port {self.target!r}: {exc}") from None
        except (serial.SerialException, OSError) as exc:
            raise DeviceLost(f"cannot open serial port {self.target}: {exc}") from None
        self._framer = self._framer_class()
        self._gaps = SequenceGaps(modulus=hatire.COUNTER_WRAP)
        self._seq = 0
        try:
            self.port.write(self._start_command)
        except (serial.SerialException, OSError) as exc:
            raise DeviceLost(f"serial port {self.target} write failed: {exc}") from None
        self.state = "connected"

    def read(self, timeout_s: float) -> list[Sample]:
        if self.port is None:
            raise DeviceLost("serial:// is not open")
        out: list[Sample] = []
        for _ in range(max(1, math.ceil(timeout_s / POLL_S))):
            try:
                data = self.port.read(1)
                if data:
                    data += self.port.read(min(self.port.in_waiting, MAX_CHUNK))
            except (serial.SerialException, OSError) as exc:
                raise DeviceLost(f"serial port {self.target} failed: {exc}") from None
            out += self._samples(data, self.clock.now_ns())
            if out:
                break
        return self.count(out)

    def _samples(self, data: bytes, t_recv: int) -> list[Pose]:
        before = self._framer.discarded
        frames = self._framer.feed(data)
        self.counters.malformed += self._framer.discarded - before
        poses = []
        for frame in frames:
            if not isinstance(frame, self._angles):
                continue  # SYNCH answers, error lines, info frames
            if isinstance(frame, hatire.HatireFrame):
                self.counters.dropped += self._gaps.see(frame.cpt)
            orientation = razor.ypr_to_quat(frame.yaw, frame.pitch, frame.roll)
            poses.append(Pose(seq=self._seq, t_host=t_recv, position=(0.0, 0.0, 0.0), orientation=orientation))
            self._seq += 1
        return poses

    def close(self) -> None:
        if self.port is not None:
            port, self.port = self.port, None
            try:
                port.close()
            except (serial.SerialException, OSError):
                pass  # the device is already gone
        self.state = "closed"
