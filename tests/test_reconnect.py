"""The one reconnect policy (drivers.reconnect): its delays and counts, and the compositor's virtual-time sources
following it on the virtual clock as DriverHost follows it in real time."""

from __future__ import annotations

import pytest

from hmdrt.clock import VirtualClock
from hmdrt.compositor.sources import Sources
from hmdrt.drivers import REGISTRY, register
from hmdrt.drivers.base import DeviceLost, Sample
from hmdrt.drivers.reconnect import Reconnect
from hmdrt.drivers.synthetic import SyntheticDriver
from hmdrt.errors import ConfigError

MS = 1_000_000


class FlakyDriver(SyntheticDriver):
    """The synthetic device, lost on the reads and opens a test schedules."""

    scheme = "flaky"
    lose_reads: set[int] = set()  # the reads (counted from 0 over the driver's life) that raise DeviceLost
    fail_opens: set[int] = set()  # the opens (0: the first) that raise DeviceLost

    def __init__(self, url, clock):
        super().__init__(url, clock)
        self.reads = self.opens = 0
        self.opened_at: list[int] = []

    def open(self) -> None:
        self.opens += 1
        if self.opens - 1 in self.fail_opens:
            raise DeviceLost("still away")
        self.opened_at.append(self.clock.now_ns())
        super().open()

    def read(self, timeout_s: float) -> list[Sample]:
        self.reads += 1
        if self.reads - 1 in self.lose_reads:
            raise DeviceLost("gone")
        return super().read(timeout_s)


@pytest.fixture
def flaky():
    register("flaky", f"{__name__}:FlakyDriver")
    yield FlakyDriver
    del REGISTRY["flaky"]
    FlakyDriver.lose_reads, FlakyDriver.fail_opens = set(), set()


def test_failed_opens_wait_doubling_delays_up_to_the_longest_and_a_working_device_reopens_at_once():
    driver = SyntheticDriver("synthetic://")
    policy = Reconnect(0.1, 0.4)
    assert [policy.lost(driver, working=False) for _ in range(4)] == [0.1, 0.2, 0.4, 0.4]
    assert policy.lost(driver, working=True) == 0.0
    assert policy.lost(driver, working=False) == 0.1  # the delay started afresh
    assert driver.counters.reconnects == 6 and driver.state == "closed"


def test_a_crash_waits_and_the_delay_starts_afresh_only_after_a_long_run():
    driver = SyntheticDriver("synthetic://")
    policy = Reconnect(0.05, 0.2)
    policy.opened(driver, 0)
    assert [policy.crashed(driver, 10 * MS) for _ in range(3)] == [0.05, 0.1, 0.2]  # crashing again at once
    policy.opened(driver, 100 * MS)
    assert policy.crashed(driver, 301 * MS) == 0.05  # it had run longer than the longest delay
    # then every reopen crashes (a stream that lies from now on): no run since, so the delays grow again, however
    # long ago the last good run began
    assert [policy.crashed(driver, (400 + k) * MS) for k in range(3)] == [0.1, 0.2, 0.2]
    assert driver.counters.crashes == 7 and driver.counters.reconnects == 0


def test_the_state_is_announced_before_the_driver_is_closed():
    seen = []
    driver = SyntheticDriver("synthetic://")
    policy = Reconnect(announce=lambda d: seen.append((d.state, d.counters.reconnects, d.counters.crashes)))
    policy.lost(driver, working=True)
    policy.crashed(driver, 0)
    assert seen == [("lost", 0, 0), ("crashed", 1, 1)]


@pytest.mark.parametrize("first, longest", [(0.0, 1.0), (2.0, 1.0), (-1.0, 1.0)])
def test_delays_must_grow_from_a_positive_first(first, longest):
    with pytest.raises(ConfigError, match="0 < first <= longest"):
        Reconnect(first, longest)


def test_virtual_time_sources_reopen_a_lost_device_at_once_then_on_the_virtual_clock(flaky):
    flaky.lose_reads, flaky.fail_opens = {3}, {1, 2}  # lost on the 4th read; the next two opens fail
    clock, got = VirtualClock(), []
    sources = Sources(["flaky://?rate=1000"], clock, True, "", lambda device, sample, now: got.append(now))
    driver = sources.polled[0]
    try:
        for _ in range(40):
            clock.advance(10 * MS)
            sources.poll()
    finally:
        sources.close()
    # opened at 0; lost at 20 ms, reopened at once (fails), then 0.1 s later (fails), then 0.2 s after that
    assert driver.opened_at == [0, 320 * MS]
    assert driver.counters.reconnects == 3
    assert got and not any(20 * MS < t < 320 * MS for t in got)  # nothing while it was away
    assert sources.counters()["flaky"]["reconnects"] == 3
