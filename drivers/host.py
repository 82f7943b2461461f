"""Running a driver against the bus: `hmdrt driver URL --bus ENDPOINT`.

The host connects a PUB socket (an XPUB, to see the ingest's subscription arrive before the first
message) to the compositor's ingest SUB, opens the driver, and publishes each
normalised sample as gaze.<device> / pose.<device>, plus status.<device> on every state change and
once a second. When the device goes away (DeviceLost) or the driver crashes (an unexpected error in its own
code, or in what its device sent), it closes the driver and opens it again as the reconnect policy says
(drivers.reconnect: at once after a working device went away, else with exponential backoff), counting reconnects
and crashes. A configuration error as the driver opens ends `hmdrt driver` with that error; a compositor's driver
thread (keep_alive) counts it as a crash and tries again, so that no stream another host publishes, however it
lies, ends the thread. A full send queue
(the compositor not keeping up) drops the newest sample and counts it, rather than blocking the device.
"""

from __future__ import annotations

import logging
import threading
import time

import zmq

from hmdrt.bus.local import find_endpoint
from hmdrt.bus.messages import encode
from hmdrt.bus.security import ClientKeys
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers import open_driver
from hmdrt.drivers.base import Counters, DeviceLost, Driver
from hmdrt.drivers.reconnect import Reconnect
from hmdrt.errors import HmdrtError

log = logging.getLogger(__name__)


class DriverHost:
    def __init__(
        self,
        url: str,
        bus: str = "",  # the ingest; "": this user's one running compositor's (hmdrt.bus.local)
        clock: Clock = MONOTONIC,
        status_period_s: float = 1.0,
        backoff_s: tuple[float, float] = (0.1, 2.0),
        queue: int = 10_000,
        context: zmq.Context | None = None,
        subscriber_wait_s: float = 1.0,
        curve: ClientKeys | None = None,  # connect as this CURVE client (an ingest with [security] needs it)
        keep_alive: bool = False,  # a configuration error as the driver opens is a crash too, restarted
    ):
        self.driver: Driver = open_driver(url, clock)
        bus = bus or find_endpoint("ingest")  # after the URL is checked: its error says more
        self.clock = clock
        self.keep_alive = keep_alive
        self.status_period_ns = int(status_period_s * 1e9)
        self.reconnect = Reconnect(*backoff_s, announce=self._announce)
        self._context = context or zmq.Context.instance()
        self._socket = self._context.socket(zmq.XPUB)
        self._socket.setsockopt(zmq.SNDHWM, queue)
        self._socket.setsockopt(zmq.LINGER, 500)
        if curve is not None:
            curve.apply(self._socket)
        self._socket.connect(bus)
        self._last_status = 0
        self._await_subscriber(subscriber_wait_s)

    def _await_subscriber(self, timeout_s: float) -> None:
        """Wait briefly for the ingest's subscription, so the first messages are not lost to the slow joiner."""
        if self._socket.poll(int(timeout_s * 1000), zmq.POLLIN):
            self._socket.recv()

    @property
    def counters(self) -> Counters:
        return self.driver.counters

    def _publish(self, message) -> bool:
        try:
            self._socket.send_multipart(encode(message, self.driver.device), flags=zmq.NOBLOCK)
            return True
        except zmq.Again:
            return False

    def _status(self, force: bool = False) -> None:
        now = self.clock.now_ns()
        if force or now - self._last_status >= self.status_period_ns:
            self._publish(self.driver.status())
            self._last_status = now

    def _announce(self, driver: Driver) -> None:
        """Publish the status of a driver that lost its device or crashed; a status that fails as well (a broken
        driver's) is left out, so that the restart goes on."""
        try:
            self._status(force=True)
        except Exception as exc:  # noqa: BLE001 - see the docstring
            log.debug("driver %s gave no status: %s: %s", driver.device, type(exc).__name__, exc)

    def _serve(self, stop: threading.Event) -> float | None:
        """Open the driver and publish its samples until `stop` is set (None) or it fails: then the seconds to wait
        before opening it again, as the reconnect policy says. A configuration error as it opens is raised, unless
        keep_alive."""
        opened = False
        try:
            self.driver.state = "connecting"
            self._status(force=True)
            self.driver.open()
            opened = True
            self.reconnect.opened(self.driver, time.monotonic_ns())
            self._status(force=True)
            while not stop.is_set():
                for sample in self.driver.read(0.05):
                    if not self._publish(sample):
                        self.driver.counters.dropped += 1
                self._status()
            return None
        except DeviceLost:
            return self.reconnect.lost(self.driver, working=opened)
        except Exception as exc:  # noqa: BLE001 - a bug in the driver, or what its device sent: restart it
            if isinstance(exc, HmdrtError) and not opened and not self.keep_alive:
                raise  # a configuration error: retrying cannot help
            return self.reconnect.crashed(self.driver, time.monotonic_ns(), exc)

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> Counters:
        """Publish until `stop` is set or duration_s passes; returns the driver's counters. A driver that
        loses its device or crashes is opened again as the reconnect policy says."""
        stop = stop or threading.Event()
        timer = threading.Timer(duration_s, stop.set) if duration_s is not None else None
        if timer:
            timer.daemon = True
            timer.start()
        try:
            while (wait_s := self._serve(stop)) is not None:
                if stop.wait(wait_s):
                    break
        finally:
            if timer:
                timer.cancel()
            self._close()
        return self.driver.counters

    def _close(self) -> None:
        """Close the driver and say so on the bus; a driver that fails to, fails in one logged line."""
        try:
            self.driver.close()
            self.driver.state = "closed"
            self._status(force=True)
        except Exception as exc:  # noqa: BLE001 - the run is over: report it, and close the socket still
            log.warning("driver %s did not close (%s: %s)", self.driver.device, type(exc).__name__, exc)
        self._socket.close()
