"""The lifecycle every emulator shares: start() binds and spawns one daemon thread, stop() joins it and
releases what was bound.

The thread runs one loop: emit everything due on the clock (_tick), then wait for and handle I/O
(_poll) until the next due time, but never longer than POLL_S, so that stop() is noticed promptly.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections import deque
from typing import Self

from hmdrt.clock import Clock
from hmdrt.drivers.base import DriverError

POLL_S = 0.05  # longest wait of the emulator thread, and so about the longest stop() takes
SENT_LOG = 65_536  # samples remembered in Emulator.sent
Address = tuple[str, int]


class Emulator(ABC):
    """A device emulator served from a daemon thread named "<name>-emulator"; a context manager."""

    name: str  # for the thread and for messages

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
