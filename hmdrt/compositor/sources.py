"""The drivers a run config starts itself.

In real time each runs under its own DriverHost thread and publishes to the compositor's ingest,
exactly as `hmdrt driver URL` would from another process. In virtual time the frame loop polls each
driver against the virtual clock instead, so every sample due by a frame's wake-up is in before the
frame samples gaze and pose: the run is a pure function of config, trace and seed.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from hmdrt.bus.security import ClientKeys
from hmdrt.clock import Clock
from hmdrt.drivers import open_driver
from hmdrt.drivers.base import DeviceLost, Driver
from hmdrt.drivers.host import DriverHost

MAX_READS = 64  # batches per driver per poll (a read returns at most a few thousand samples)


class Sources:
    def __init__(
        self,
        urls: list[str],
        clock: Clock,
        virtual: bool,
        ingest: str,
        sink: Callable[[str, object, int], None],
        keys: ClientKeys | None = None,  # CURVE keys of a secured ingest
    ):
        self._clock = clock
        self._sink = sink
        self._stop = threading.Event()
        self.hosts: list[DriverHost] = []
        self.polled: list[Driver] = []
        self._threads: list[threading.Thread] = []
        for url in urls:
            if virtual:
                driver = open_driver(url, clock)
                driver.open()
                self.polled.append(driver)
            else:
                self.hosts.append(DriverHost(url, ingest, subscriber_wait_s=0.5, curve=keys))
        for host in self.hosts:
            thread = threading.Thread(target=host.run, args=(self._stop,), name=f"driver-{host.driver.device}")
            thread.daemon = True
            thread.start()
            self._threads.append(thread)

    def wait_connected(self, timeout_s: float) -> bool:
        """Wait up to timeout_s for the hosted drivers to connect (a trace loaded, a device answering), so
        that their start-up work is done before the first frame; whether all did."""
        deadline = time.monotonic() + timeout_s
        while any(host.driver.state != "connected" for host in self.hosts):
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.01)
        return True

    def poll(self) -> None:
        """Virtual time: hand the compositor every sample due by now."""
        now = self._clock.now_ns()
        for driver in self.polled:
            for _ in range(MAX_READS):
                try:
                    samples = driver.read(0.0)
                except DeviceLost:
                    driver.close()
                    driver.counters.reconnects += 1
                    driver.open()
                    break
                if not samples:
                    break
                for sample in samples:
                    self._sink(driver.device, sample, now)

    def counters(self) -> dict[str, dict]:
        """{device: {samples, dropped, invalid, malformed, reconnects}} of the drivers started here."""
        drivers = [host.driver for host in self.hosts] + self.polled
        return {d.device: dict(vars(d.counters)) for d in drivers}

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
        for driver in self.polled:
            driver.close()
