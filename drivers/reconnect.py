"""The one reconnect policy: when a driver whose device went away, or whose own code crashed, is opened again,
and the counting of both.

A device lost while it was working is reopened at once. An open that fails because the device is still away,
and a crash, wait the current delay first; the delay starts at `first_s` and doubles after each wait, up to
`longest_s`. It starts afresh when a reopened device works again, and after a crash of a driver that had run
longer than `longest_s`, so only a driver that crashes again at once waits longer each time.

DriverHost follows it in real time (waiting on its stop event); the compositor's Sources follow it in virtual
time, where the waits are on the virtual clock.
"""

from __future__ import annotations

from collections.abc import Callable

from hmdrt.drivers.base import Driver
from hmdrt.errors import ConfigError


class Reconnect:
    """The delays and counts of reopening one driver.

    announce(driver) is called once the driver's state reads "lost" or "crashed", before the driver is closed
    (a host publishes its status there); a crash is counted by then, a reconnect only once the driver is closed."""

    def __init__(
        self,
        first_s: float = 0.1,
        longest_s: float = 2.0,
        announce: Callable[[Driver], None] | None = None,
    ):
        if not 0.0 < first_s <= longest_s:
            raise ConfigError(f"reconnect delays need 0 < first <= longest, got {first_s} and {longest_s} s")
        self.first_s = first_s
        self.longest_s = longest_s
        self.delay_s = first_s  # the wait before the next reopen that is not at once
        self._announce = announce or (lambda driver: None)
        self._opened_ns: int | None = None

    def opened(self, driver: Driver, now_ns: int) -> None:
        """The driver opened at now_ns (any clock, as long as crashed() is given the same one)."""
        driver.state = "connected"
        self._opened_ns = now_ns

    def lost(self, driver: Driver, working: bool) -> float:
        """The device went away, while `working` or on an open that failed: close the driver and count a
        reconnect. Returns the seconds to wait before opening it again."""
        driver.state = "lost"
        self._announce(driver)
        driver.close()
        driver.counters.reconnects += 1
        if working:
            self.delay_s = self.first_s
            return 0.0
        return self._wait()

    def crashed(self, driver: Driver, now_ns: int) -> float:
        """The driver's own code raised: count a crash and close the driver (a close that fails as well is
        ignored: the driver is already broken). Returns the seconds to wait before opening it again."""
        driver.counters.crashes += 1
        driver.state = "crashed"
        self._announce(driver)
        if self._opened_ns is not None and now_ns - self._opened_ns > self.longest_s * 1e9:
            self.delay_s = self.first_s
        try:
            driver.close()
        except Exception:  # noqa: BLE001 - its close must not stop the restart
            pass
        return self._wait()

    def _wait(self) -> float:
        wait = self.delay_s
        self.delay_s = min(2 * wait, self.longest_s)
        return wait
