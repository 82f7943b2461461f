"""Running a driver against the bus: `hmdrt driver URL --bus ENDPOINT`.

The host connects a PUB socket (an XPUB, to see the ingest's subscription arrive before the first
message) to the compositor's ingest SUB, opens the driver, and publishes each
normalised sample as gaze.<device> / pose.<device>, plus status.<device> on every state change and
once a second. When the device goes away (DeviceLost) it closes the driver and reopens it with
exponential backoff, counting reconnects; configuration errors are not retried. A full send queue
(the compositor not keeping up) drops the newest sample and counts it, rather than blocking the device.
"""

from __future__ import annotations

import threading

import zmq

from drivers import open_driver
from drivers.base import MONOTONIC, Clock, Counters, DeviceLost, Driver
from hmdrt.bus import INGEST
from hmdrt.bus.messages import encode


class DriverHost:
    def __init__(
        self,
        url: str,
        bus: str = INGEST,
        clock: Clock = MONOTONIC,
        status_period_s: float = 1.0,
        backoff_s: tuple[float, float] = (0.1, 2.0),
        queue: int = 10_000,
        context: zmq.Context | None = None,
        subscriber_wait_s: float = 1.0,
    ):
        self.driver: Driver = open_driver(url, clock)
        self.clock = clock
        self.status_period_ns = int(status_period_s * 1e9)
        self.backoff_s = backoff_s
        self._context = context or zmq.Context.instance()
        self._socket = self._context.socket(zmq.XPUB)
        self._socket.setsockopt(zmq.SNDHWM, queue)
        self._socket.setsockopt(zmq.LINGER, 500)
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

    def _open(self, stop: threading.Event) -> bool:
        """Open the driver, retrying with backoff while the device is away; False if stopped first."""
        delay = self.backoff_s[0]
        while not stop.is_set():
            self.driver.state = "connecting"
            self._status(force=True)
            try:
                self.driver.open()
                self.driver.state = "connected"
                self._status(force=True)
                return True
            except DeviceLost:
                self.driver.state = "lost"
                self.driver.close()
                self.driver.counters.reconnects += 1
                self._publish(self.driver.status())
                if stop.wait(delay):
                    break
                delay = min(2 * delay, self.backoff_s[1])
        return False

    def run(self, stop: threading.Event | None = None, duration_s: float | None = None) -> Counters:
        """Publish until `stop` is set or duration_s passes; returns the driver's counters."""
        stop = stop or threading.Event()
        timer = threading.Timer(duration_s, stop.set) if duration_s is not None else None
        if timer:
            timer.daemon = True
            timer.start()
        try:
            while self._open(stop):
                try:
                    while not stop.is_set():
                        for sample in self.driver.read(0.05):
                            if not self._publish(sample):
                                self.driver.counters.dropped += 1
                        self._status()
                except DeviceLost:
                    self.driver.state = "lost"
                    self._status(force=True)
                    self.driver.close()
                    self.driver.counters.reconnects += 1
                    continue
                break
        finally:
            if timer:
                timer.cancel()
            self.driver.close()
            self.driver.state = "closed"
            self._status(force=True)
            self._socket.close()
        return self.driver.counters
