"""The drivers a run config starts itself.

In real time each runs under its own DriverHost thread and publishes to the compositor's ingest,
exactly as `hmdrt driver URL` would from another process. In virtual time the frame loop polls each
driver against the virtual clock instead, so every sample due by a frame's wake-up is in before the
frame samples gaze and pose: the run is a pure function of config, trace and seed. Either way a driver whose
device goes away, or that raises (a crash, counted), is opened again as drivers.reconnect says; in virtual time its
waits are on the virtual clock. No driver ends the run once it has started.
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
from hmdrt.drivers.reconnect import Reconnect

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
        self._reconnects: dict[Driver, Reconnect] = {}  # of the polled drivers
        self._reopen_ns: dict[Driver, int] = {}  # when a polled driver whose device went away opens again
        self._threads: list[threading.Thread] = []
        for url in urls:
            if virtual:
                driver = open_driver(url, clock)
                driver.open()
                self._reconnects[driver] = Reconnect()
                self._reconnects[driver].opened(driver, clock.now_ns())
                self.polled.append(driver)
            else:
                self.hosts.append(DriverHost(url, ingest, subscriber_wait_s=0.5, curve=keys, keep_alive=True))
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
            if not self._ready(driver, now):
                continue
            for _ in range(MAX_READS):
                try:
                    samples = driver.read(0.0)
                except DeviceLost:
                    self._lost(driver, now, working=True)
                    self._ready(driver, now)  # a device that was working opens again at once
                    break
                except Exception as exc:  # noqa: BLE001 - a driver's own error: restart it, as a host would
                    self._crashed(driver, now, exc)
                    break
                if not samples:
                    break
                for sample in samples:
                    self._sink(driver.device, sample, now)

    def _lost(self, driver: Driver, now_ns: int, working: bool) -> None:
        """Close a polled driver whose device went away, and note when its reconnect policy opens it again."""
        self._reopen_ns[driver] = now_ns + round(self._reconnects[driver].lost(driver, working) * 1e9)

    def _crashed(self, driver: Driver, now_ns: int, error: Exception) -> None:
        """Count and close a polled driver that raised, and note when its reconnect policy opens it again."""
        self._reopen_ns[driver] = now_ns + round(self._reconnects[driver].crashed(driver, now_ns, error) * 1e9)

    def _ready(self, driver: Driver, now_ns: int) -> bool:
        """Whether a polled driver is open: it was, or it was due to open again by now_ns and did."""
        due_ns = self._reopen_ns.get(driver)
        if due_ns is None:
            return True
        if now_ns < due_ns:
            return False
        try:
            driver.open()
        except DeviceLost:
            self._lost(driver, now_ns, working=False)
            return False
        except Exception as exc:  # noqa: BLE001 - see poll
            self._crashed(driver, now_ns, exc)
            return False
        del self._reopen_ns[driver]
        self._reconnects[driver].opened(driver, now_ns)
        return True

    def counters(self) -> dict[str, dict]:
        """{device: {samples, dropped, invalid, malformed, reconnects, crashes}} of the drivers started here."""
        drivers = [host.driver for host in self.hosts] + self.polled
        return {d.device: dict(vars(d.counters)) for d in drivers}

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=5.0)
        for driver in self.polled:
            driver.close()
