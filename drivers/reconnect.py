"""The one reconnect policy: when a driver whose device went away, or whose own code crashed, is opened again,
the counting of both, and the one log line of each crash.

A device lost while it was working is reopened at once. An open that fails because the device is still away,
and a crash, wait the current delay first; the delay starts at `first_s` and doubles after each wait, up to
`longest_s`. It starts afresh when a reopened device works again, and after a crash of a driver that had run
longer than `longest_s`, so only a driver that crashes again at once waits longer each time.

DriverHost follows it in real time (waiting on its stop event); the compositor's Sources follow it in virtual
time, where the waits are on the virtual clock.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

from hmdrt.drivers.base import Driver
from hmdrt.errors import ConfigError

log = logging.getLogger(__name__)


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
        self._opened_ns = None
        self._announce(driver)
        _close(driver)
        driver.counters.reconnects += 1
        if working:
            self.delay_s = self.first_s
            return 0.0
        return self._wait()

    def crashed(self, driver: Driver, now_ns: int, error: BaseException | None = None) -> float:
        """The driver's own code raised `error`: count a crash, log it in one line (the traceback at debug level)
        and close the driver. Returns the seconds to wait before opening it again."""
        driver.counters.crashes += 1
        driver.state = "crashed"
        self._announce(driver)
        if self._opened_ns is not None and now_ns - self._opened_ns > self.longest_s * 1e9:
            self.delay_s = self.first_s
        self._opened_ns = None  # until it opens again: crashes while reopening wait longer each time
        _close(driver)
        wait = self._wait()
        if error is not None:
            what = " ".join(f"{type(error).__name__}: {error}".split())  # one line, whatever the message holds
            log.warning("driver %s crashed (%s); restarting in %.2g s", driver.device, what, wait)
            log.debug("driver %s crashed", driver.device, exc_info=error)
        return wait

    def _wait(self) -> float:
        wait = self.delay_s
        self.delay_s = min(2 * wait, self.longest_s)
        return wait


def _close(driver: Driver) -> None:
    """Close a driver that lost its device or crashed; a close that fails as well is logged (at debug level) and
    ignored: the driver is already broken, and its reopening must go on."""
    try:
        driver.close()
    except Exception as exc:  # noqa: BLE001 - see the docstring
        log.debug("driver %s did not close: %s: %s", driver.device, type(exc).__name__, exc)
