"""The lifecycle every emulator shares: start() binds and spawns one daemon thread, stop() joins it and
releases what was bound.

The thread runs one loop: emit everything due on the clock (_tick), then wait for and handle I/O
(_poll) until the next due time, but never longer than POLL_S, so that stop() is noticed promptly.

An emulator class declares the devices `hmdrt emulate DEVICE` builds with it (`emulates`: name, default port,
rate and latency) and builds one from what the command asked for (`emulate`); the registry in
drivers.emulators reads both and knows no device by name.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass
from typing import ClassVar, Self

from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DriverError
from hmdrt.drivers.emulators.feed import GazeFeed
from hmdrt.errors import ConfigError

POLL_S = 0.05  # longest wait of the emulator thread, and so about the longest stop() takes
SENT_LOG = 65_536  # samples remembered in Emulator.sent
Address = tuple[str, int]
GAZE_FLAGS = ("--trace", "--offset", "--noise", "--latency")  # what only an emulator of gaze takes
RANGES = {"--offset": (-45.0, 45.0), "--noise": (0.0, 10.0), "--latency": (0.0, 1000.0)}


@dataclass(frozen=True)
class Emulated:
    """A device an emulator class serves, as its class declares it."""

    name: str  # what `hmdrt emulate` calls it
    rate_hz: float  # default sample rate
    port: int | None = None  # default port; None: it is reached without one
    latency_ms: float | None = None  # default capture-to-send latency of its gaze; None: it sends no gaze
    reached: str = ""  # what it is, as an error for an option it takes no value for says it

    @property
    def refuses(self) -> tuple[str, ...]:
        """The `hmdrt emulate` options it takes no value for."""
        refused = () if self.port is not None else ("--port",)
        return refused if self.latency_ms is not None else (*refused, *GAZE_FLAGS)


@dataclass(frozen=True)
class EmulatorOptions:
    """What `hmdrt emulate` asks of an emulator (make_emulator's keywords); None: the device's default."""

    host: str = "127.0.0.1"
    port: int | None = None
    trace: str | None = None
    seed: int = 0
    rate_hz: float | None = None
    offset_deg: float | None = None
    noise_deg: float | None = None
    latency_ms: float | None = None
    clock: Clock = MONOTONIC

    def check(self, device: Emulated) -> None:
        """A ConfigError for an option `device` takes no value for, or a value out of range."""
        given = {
            "--port": self.port,
            "--trace": self.trace,
            "--offset": self.offset_deg,
            "--noise": self.noise_deg,
            "--latency": self.latency_ms,
        }
        if unused := [flag for flag, value in given.items() if value is not None and flag in device.refuses]:
            raise ConfigError(f"the {device.name} emulator {device.reached}; it takes no {unused[0]}")
        if self.port is not None and not 0 <= self.port <= 65535:
            raise ConfigError(f"--port must be within 0 and 65535 (0: any free port), got {self.port}")
        for flag, (lo, hi) in RANGES.items():
            if (value := given[flag]) is not None and not lo <= value <= hi:
                raise ConfigError(f"{flag} must be within {lo:g} and {hi:g}, got {value}")

    def port_for(self, device: Emulated) -> int | None:
        return device.port if self.port is None else self.port

    def rate_for(self, device: Emulated) -> float:
        return device.rate_hz if self.rate_hz is None else self.rate_hz

    def feed(self, device: Emulated) -> GazeFeed:
        """The device's gaze: from the trace or the synthetic gaze of the seed, degraded as asked."""
        return GazeFeed(
            self.rate_for(device),
            trace=self.trace,
            seed=self.seed,
            offset_deg=self.offset_deg or 0.0,
            noise_deg=self.noise_deg or 0.0,
            latency_ms=device.latency_ms if self.latency_ms is None else self.latency_ms,
            clock=self.clock,
        )


class Emulator(ABC):
    """A device emulator served from a daemon thread named "<name>-emulator"; a context manager."""

    name: str  # for the thread and for messages
    emulates: ClassVar[tuple[Emulated, ...]] = ()  # the devices `hmdrt emulate` builds with this class

    @classmethod
    def emulate(cls, device: Emulated, options: EmulatorOptions) -> Emulator:
        """An emulator of `device` (one of cls.emulates) as `options` ask, not yet started; the options are
        checked against the device's declaration already."""
        raise NotImplementedError(f"{cls.__name__} emulates no device for `hmdrt emulate`")

    def __init__(self, clock: Clock):
        self.clock = clock
        self.epoch_ns = 0  # the host time at which the emulated device's clock read zero
        # (device time ns, host time ns) of each gaze sample as it went out, newest last: where the
        # device's own latency ends, for measuring what a driver and the bus add downstream
        self.sent: deque[tuple[int, int]] = deque(maxlen=SENT_LOG)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def running(self) -> bool:
        return self._thread is not None

    @property
    @abstractmethod
    def url(self) -> str:
        """The driver URL that connects to this emulator, once started."""

    def start(self) -> Self:
        """Bind the emulator's resources and serve them from a daemon thread."""
        if self._thread is not None:
            raise DriverError(f"the {self.name} emulator is already running")
        self._bind()
        self._stop.clear()
        self._thread = threading.Thread(target=self._serve, name=f"{self.name}-emulator", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop serving and release what start() bound; safe to call twice."""
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._thread = None
        self._release()

    def __enter__(self) -> Self:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _log_sent(self, t_dev_ns: int) -> None:
        self.sent.append((t_dev_ns, self.clock.now_ns()))

    def _serve(self) -> None:
        while not self._stop.is_set():
            next_due_ns = self._tick(self.clock.now_ns())
            self._poll(min(max(next_due_ns - self.clock.now_ns(), 0) / 1e9, POLL_S))

    @abstractmethod
    def _bind(self) -> None:
        """Acquire sockets or devices and reset the emulated device's state; runs in start()."""

    @abstractmethod
    def _release(self) -> None:
        """Close what _bind acquired; runs in stop(), once the thread has ended."""

    @abstractmethod
    def _tick(self, now_ns: int) -> int:
        """Emit everything due at now_ns; return the clock time (ns) at which the next emission is due."""

    @abstractmethod
    def _poll(self, timeout_s: float) -> None:
        """Wait at most timeout_s for I/O and handle what arrived."""


class NetworkEmulator(Emulator):
    """An emulator listening at host:port (port 0: a free one, see `address` once started)."""

    driver_options = ""  # the query its driver needs, e.g. "?listen=0"

    @classmethod
    def emulate(cls, device: Emulated, options: EmulatorOptions) -> Emulator:
        """At the device's port unless another is asked for, its gaze from options.feed, at the feed's rate."""
        feed, port = options.feed(device), options.port_for(device)
        return cls(host=options.host, port=port, feed=feed, rate_hz=feed.rate_hz, clock=options.clock)

    def __init__(self, host: str, port: int, clock: Clock):
        super().__init__(clock)
        self.host, self.port = host, port
        self._address: Address | None = None  # set by _bind

    @property
    def address(self) -> Address:
        """The (host, port) clients connect to."""
        if self._address is None:
            raise DriverError(f"the {self.name} emulator is not running; call start() first")
        return self._address

    @property
    def url(self) -> str:
        host, port = self.address
        return f"{self.name}://{host}:{port}{self.driver_options}"

    def stop(self) -> None:
        super().stop()
        self._address = None
