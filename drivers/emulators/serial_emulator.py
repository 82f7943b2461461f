"""A Razor AHRS or HATIRE head tracker on a real pseudo-terminal (docs/protocols.md, Razor and HATIRE).

    with SerialTrackerEmulator("razor", seed=1) as emu:
        open_driver(f"serial://{emu.device_path}?protocol=razor")

The emulator opens a pty pair (os.openpty, raw mode), writes frames of replay.synthetic's head motion to
the master side at the device rate, and answers the commands a host writes to the slave side, whose
name is `device_path`: a serial device any program can open. A background daemon thread does both and
stops when stop() sets its event; the pty is closed on stop, so a reader sees the device vanish.

A board that resets when the port opens (boot_s > 0) sends nothing and drops what the host writes
(counted in `ignored_bytes`) for boot_s after start, as an Arduino in its bootloader does; with
streaming=False the firmware then waits for a start command (Razor built with OUTPUT__STARTUP_STREAM_ON
false). Razor (text output only): streams `#YPR=` lines like the firmware; `#o0`/`#o1` stream off/on,
`#f` sends one frame on the next tick, `#s<xy>` answers `#SYNCH<xy>`; other commands are accepted and
ignored. HATIRE, after HATino: boots with info frames 2000 (version) and 5000 (begin) and streams; `S`
answers 5001, restarts the counter and streams; `s` answers 5002 and stops; `R` answers 5003 and boots
again; `C` zeroes the next five frames (calibration); `V` answers 2000; `I` prints plain text lines. Its
rotation fields are laid out for opentrack's default axis mapping (hatire.AxisMapping()). When the host
does not read, the pty fills up and frames are dropped (`overflows`).
"""

from __future__ import annotations

import os
import select
import tty
from collections.abc import Iterator

from hmdrt.bus.messages import Pose
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.emulators.base import Emulated, Emulator, EmulatorOptions
from hmdrt.drivers.protocols import hatire, razor
from hmdrt.errors import ConfigError
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource

MAX_COMMAND_CHUNK = 256


class _Razor:
    def __init__(self, streaming: bool) -> None:
        self.streaming = streaming
        self._one_frame = False
        self._pending = b""

    def boot(self) -> bytes:
        return b""

    def command(self, data: bytes) -> bytes:
        commands, self._pending = razor.parse_commands(self._pending + data)
        reply = b""
        for c in commands:
            if c in ("o0", "o1"):
                self.streaming = c == "o1"
            elif c == "f":
                self._one_frame = True
            elif c.startswith("s"):
                reply += razor.encode_synch(c[1:])
        return reply

    def frame(self, orientation: tuple[float, ...]) -> bytes:
        if not (self.streaming or self._one_frame):
            return b""
        self._one_frame = False
        return razor.encode_ypr(*razor.quat_to_ypr(orientation))


class _Hatire:
    VERSION = "HAT V 1.10"
    CALIBRATION_FRAMES = 5

    def __init__(self, streaming: bool) -> None:
        self.streaming_at_boot = self.streaming = streaming
        self.cpt = 0
        self._calibrating = 0

    def boot(self) -> bytes:
        self.streaming, self.cpt = self.streaming_at_boot, 0
        return hatire.encode_info(hatire.CODE_VERSION, self.VERSION) + hatire.encode_info(
            hatire.CODE_BEGIN, "HAT BEGIN"
        )

    def command(self, data: bytes) -> bytes:
        reply = b""
        for c in (data[i : i + 1] for i in range(len(data))):
            if c == hatire.START:
                self.streaming, self.cpt = True, 0
                reply += hatire.encode_info(hatire.CODE_START, "HAT START")
            elif c == hatire.STOP:
                self.streaming = False
                reply += hatire.encode_info(hatire.CODE_STOP, "HAT STOP")
            elif c == hatire.RESET:
                reply += hatire.encode_info(hatire.CODE_RESET, "HAT RESET") + self.boot()
            elif c == hatire.CALIBRATE:
                self._calibrating = self.CALIBRATION_FRAMES
            elif c == hatire.VERSION:
                reply += hatire.encode_info(hatire.CODE_VERSION, self.VERSION)
            elif c == hatire.INFO:
                reply += f"\r\nVersion : \t{self.VERSION}\r\n".encode("ascii")
        return reply

    def frame(self, orientation: tuple[float, ...]) -> bytes:
        if not self.streaming:
            return b""
        fields = hatire.AxisMapping().rotation_fields(*hatire.quat_to_opentrack(orientation))
        if self._calibrating:
            self._calibrating -= 1
            fields = (0.0, 0.0, 0.0)
        frame = hatire.encode_frame(hatire.HatireFrame(self.cpt, *fields))
        self.cpt = (self.cpt + 1) % hatire.COUNTER_WRAP
        return frame


class SerialTrackerEmulator(Emulator):
    """A Razor AHRS ("razor") or HATIRE ("hatire") tracker behind the pty named by device_path."""

    DEVICES = {"razor": (_Razor, razor.RATE_HZ), "hatire": (_Hatire, hatire.RATE_HZ)}
    emulates = tuple(
        Emulated(protocol, rate_hz=rate_hz, reached="is a head tracker on a pseudo-terminal")
        for protocol, (_, rate_hz) in DEVICES.items()
    )

    def __init__(
        self,
        protocol: str = "razor",
        rate_hz: float | None = None,
        seed: int = 0,
        clock: Clock = MONOTONIC,
        boot_s: float = 0.0,
        streaming: bool = True,
    ):
        if protocol not in self.DEVICES:
            raise ConfigError(f"serial emulator protocol must be razor or hatire, got {protocol!r}")
        device, default_rate = self.DEVICES[protocol]
        self.rate_hz = default_rate if rate_hz is None else float(rate_hz)
        if not 1.0 <= self.rate_hz <= 1000.0:
            raise ConfigError(f"serial emulator rate must be within 1 and 1000 Hz, got {self.rate_hz}")
        if not 0.0 <= boot_s <= 60.0:
            raise ConfigError(f"serial emulator boot time must be within 0 and 60 s, got {boot_s}")
        super().__init__(clock)
        self.protocol = self.name = protocol
        self._device = device(streaming)
        self._boot_ns = round(boot_s * 1e9)
        self.ignored_bytes = 0  # what the host wrote while the board booted
        source = SyntheticSource(SyntheticConfig(seed=seed, rate_hz=self.rate_hz, head=True, blink_rate_hz=0.0))
        self._poses: Iterator[Pose] = (s for s in source.samples() if isinstance(s, Pose))
        self._period_ns = int(1e9 / self.rate_hz)
        self._master = self._slave = -1
        self.device_path: str | None = None
        self.frames_sent = 0
        self.overflows = 0

    @classmethod
    def emulate(cls, device: Emulated, options: EmulatorOptions) -> SerialTrackerEmulator:
        """The device's board at its rate unless another is asked for, with the synthetic head motion of the seed."""
        return cls(device.name, rate_hz=options.rate_for(device), seed=options.seed, clock=options.clock)

    @property
    def url(self) -> str:
        return f"serial://{self.device_path}?protocol={self.protocol}"

    def _bind(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.device_path = os.ttyname(self._slave)
        self._booted_ns = self.clock.now_ns() + self._boot_ns
        self._booting = True
        self._due_ns = self._booted_ns

    def _release(self) -> None:
        os.close(self._master)
        os.close(self._slave)
        self._master = self._slave = -1

    def _write(self, data: bytes) -> None:
        if not data:
            return
        try:
            if os.write(self._master, data) < len(data):
                self.overflows += 1
        except BlockingIOError:
            self.overflows += 1

    def _tick(self, now_ns: int) -> int:
        if self._booting and now_ns >= self._booted_ns:
            self._booting = False
            self._write(self._device.boot())
        if now_ns >= self._due_ns:
            frame = self._device.frame(next(self._poses).orientation)
            self._write(frame)
            self.frames_sent += bool(frame)
            self._due_ns += self._period_ns
            if self._due_ns < now_ns:  # fell behind: keep the rate rather than sending a burst
                self._due_ns = now_ns + self._period_ns
        return self._due_ns

    def _poll(self, timeout_s: float) -> None:
        readable, _, _ = select.select([self._master], [], [], timeout_s)
        if not readable:
            return
        try:
            data = os.read(self._master, MAX_COMMAND_CHUNK)
        except OSError:  # nothing to read after all
            return
        if self._booting:
            self.ignored_bytes += len(data)
            return
        self._write(self._device.command(data))
