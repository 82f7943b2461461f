"""serial://: Razor AHRS and HATIRE head trackers over a serial port (docs/protocols.md, Razor and HATIRE).

    serial:///dev/ttyUSB0?protocol=razor          a device path (three slashes: the URL path is the device)
    serial://?port=loop://&protocol=hatire        any pyserial URL (loop://, socket://, spy://...) in port=

The port is opened with pyserial's serial_for_url at 57600 baud for Razor and 115200 for HATIRE unless
baud= says otherwise. On open the driver sends the start command (Razor `#ot#o1#s00`: text frames, streaming
on, a sync token; HATIRE `S`) and sends it again every 200 ms until the first angle frame arrives, as the Razor
firmware's own host code does for a board that resets when the port opens and ignores input while it boots. A
device that sends no angle frame within 5 s is reported: a warning in the log and DeviceLost (the host counts
a reconnect and opens the port again). Bytes are framed incrementally (drivers.protocols.razor / hatire);
bytes that belong to no valid frame are counted in counters.malformed (in bytes). Angle frames become Pose
samples in the head frame: Razor's through razor.ypr_to_quat; HATIRE's through the axis mapping of
opentrack's tracker-hatire (hatire.AxisMapping, options yaw_axis= ... z_axis= and invert=, parsed once),
translation in opentrack's centimetres when mapped, else position (0, 0, 0). Neither device sends a
timestamp, so t_dev is None and t_host is the time the bytes were read. HATIRE's frame counter (0..999,
wrapping) gives lost frames in counters.dropped. A read or write error, or the device going away, raises
DeviceLost.
"""

from __future__ import annotations

import logging
import math
import time

import serial

from hmdrt.bus.messages import Pose
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DeviceLost, Driver, DriverUrl, Sample, SequenceGaps
from hmdrt.drivers.protocols import hatire, razor
from hmdrt.errors import ConfigError

log = logging.getLogger(__name__)

MAX_CHUNK = 4096
POLL_S = 0.01  # pyserial read timeout; read(timeout_s) waits in steps of this
RESEND_S = 0.2  # the start command goes again after this long without an angle frame (Razor's C++ host: 200 ms)
START_TIMEOUT_S = 5.0  # no angle frame this long after open: the device is reported (Razor's C++ host: 5000 ms)

PROTOCOLS = {
    "razor": (razor.BAUD, razor.START, razor.RazorFramer, razor.Ypr),
    "hatire": (hatire.BAUD, hatire.START, hatire.HatireFramer, hatire.HatireFrame),
}
MAPPING_OPTIONS = tuple(f"{axis}_axis" for axis in hatire.AXES) + ("invert",)


class SerialDriver(Driver):
    scheme = "serial"
    grammar = (
        "serial:///dev/ttyUSB0?protocol=razor|hatire&baud=N&name=DEVICE "
        "or serial://?port=PYSERIAL_URL&protocol=razor|hatire&baud=N (e.g. port=loop://); "
        "protocol is required; baud defaults to 57600 for razor, 115200 for hatire; hatire only: "
        "yaw_axis=, pitch_axis=, roll_axis=, x_axis=, y_axis=, z_axis= (the frame field 0, 1, 2 or off; "
        "opentrack's defaults yaw 0, pitch 2, roll 1, x y z off) and invert=AXIS,... (e.g. invert=yaw,roll)"
    )
    options = {
        "protocol": (str, "", None, None),
        "baud": (int, None, 50, 4_000_000),
        "port": (str, "", None, None),
        **dict.fromkeys(MAPPING_OPTIONS, (str, None, None, None)),
    }

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        super().__init__(url, clock)
        protocol = self.opt["protocol"]
        if protocol not in PROTOCOLS:
            raise ConfigError(f"serial:// needs protocol=razor or protocol=hatire, got {protocol!r}; {self.grammar}")
        if self.url.netloc:
            raise ConfigError(f"serial:// takes the device as the URL path (serial:///dev/ttyUSB0); {self.grammar}")
        if bool(self.url.path) == bool(self.opt["port"]):
            raise ConfigError(f"serial:// needs a device path or port=, not both or neither; {self.grammar}")
        default_baud, self._start_command, self._framer_class, self._angles = PROTOCOLS[protocol]
        self.mapping = self._mapping(protocol)
        self.target = self.url.path or self.opt["port"]
        self.baud = self.opt["baud"] or default_baud
        self.port: serial.SerialBase | None = None  # the open pyserial port (with loop://, tests write into it)
        self.start_commands = 0  # start commands sent since open: 1, and more while the device sends no angle frame
        self._streaming = False  # an angle frame arrived since open

    def _mapping(self, protocol: str) -> hatire.AxisMapping:
        """HATIRE's axis mapping from the URL's options; a ConfigError names a bad one."""
        given = {name: self.opt[name] for name in MAPPING_OPTIONS if self.opt[name] is not None}
        if given and protocol != "hatire":
            raise ConfigError(f"serial:// option {sorted(given)[0]} is for protocol=hatire only; {self.grammar}")
        fields = {name.removesuffix("_axis"): text for name, text in given.items() if name != "invert"}
        try:
            return hatire.AxisMapping.parse(fields, given.get("invert", ""))
        except ValueError as exc:
            raise ConfigError(f"serial:// {exc}; {self.grammar}") from None

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
        self._streaming, self.start_commands = False, 0
        self._opened_at = time.monotonic()
        self._send_start()
        self.state = "connected"

    def _send_start(self) -> None:
        try:
            self.port.write(self._start_command)
        except (serial.SerialException, OSError) as exc:
            raise DeviceLost(f"serial port {self.target} write failed: {exc}") from None
        self.start_commands += 1
        self._started_at = time.monotonic()

    def _keep_starting(self) -> None:
        """Before the first angle frame: send the start command again every RESEND_S, and report a device that has
        sent none START_TIMEOUT_S after open (a warning, then DeviceLost)."""
        now = time.monotonic()
        if self._streaming or now - self._started_at < RESEND_S:
            return
        if now - self._opened_at >= START_TIMEOUT_S:
            message = (
                f"serial port {self.target} ({self.opt['protocol']}) sent no angle frame within {START_TIMEOUT_S:g} s "
                f"of opening, after {self.start_commands} start commands {self._start_command!r}"
            )
            log.warning("%s: treated as lost", message)
            raise DeviceLost(message)
        self._send_start()

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
            self._keep_starting()
        return self.count(out)

    def _samples(self, data: bytes, t_recv: int) -> list[Pose]:
        before = self._framer.discarded
        frames = self._framer.feed(data)
        self.counters.malformed += self._framer.discarded - before
        poses = []
        for frame in frames:
            if not isinstance(frame, self._angles):
                continue  # SYNCH answers, error lines, info frames
            self._streaming = True
            if isinstance(frame, hatire.HatireFrame):
                self.counters.dropped += self._gaps.see(frame.cpt)
                orientation = hatire.opentrack_to_quat(*self.mapping.angles(frame))
                position = hatire.opentrack_to_position(*self.mapping.translation(frame))
            else:
                orientation, position = razor.ypr_to_quat(frame.yaw, frame.pitch, frame.roll), (0.0, 0.0, 0.0)
            poses.append(Pose(seq=self._seq, t_host=t_recv, position=position, orientation=orientation))
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
