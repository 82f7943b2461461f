"""synthetic://?seed=1&rate=250: the seeded gaze and head generator (replay.synthetic) as a device.

Samples are released when the driver's clock reaches their time, so the stream runs in real time on
the host clock and in lock-step with a virtual clock when the compositor injects one.
"""

from __future__ import annotations

from hmdrt.drivers.base import Driver, Sample
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource


class SyntheticDriver(Driver):
    scheme = "synthetic"
    grammar = (
        "synthetic://?seed=N&rate=HZ&noise=DEG&offset=DEG&latency=MS&blinks=PER_S&head=0|1&name=DEVICE "
        "(defaults seed=0 rate=250 noise=0.1 offset=0 latency=0 blinks=0.25 head=1)"
    )
    options = {
        "seed": (int, 0, 0, 2**31 - 1),
        "rate": (float, 250.0, 1.0, 10_000.0),
        "noise": (float, 0.1, 0.0, 10.0),
        "offset": (float, 0.0, -20.0, 20.0),
        "latency": (float, 0.0, 0.0, 1000.0),
        "blinks": (float, 0.25, 0.0, 10.0),
        "head": (bool, True, None, None),
    }

    def open(self) -> None:
        o = self.opt
        config = SyntheticConfig(
            seed=o["seed"],
            rate_hz=o["rate"],
            noise_deg=o["noise"],
            offset_deg=(o["offset"], 0.0),
            blink_rate_hz=o["blinks"],
            head=o["head"],
        )
        self._stream = SyntheticSource(config).samples(self.clock.now_ns())
        self._pending: Sample | None = None
        self.state = "connected"

    def read(self, timeout_s: float) -> list[Sample]:
        deadline = self.clock.now_ns() + int(timeout_s * 1e9)
        out: list[Sample] = []
        while True:
            sample = self._pending or next(self._stream)
            self._pending = None
            now = self.clock.now_ns()
            if sample.t_host <= now:
                out.append(sample)
                continue
            self._pending = sample
            if out or now >= deadline:
                return self.count(out)
            self.clock.sleep_until(min(sample.t_host, deadline))
            if self.clock.now_ns() == now:  # a virtual clock: nothing more is due until it advances
                return self.count(out)

    def close(self) -> None:
        self.state = "closed"
