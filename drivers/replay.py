"""replay://PATH?speed=1&loop=0&skip=0&use_source_ts=0&tracker=PRESET: a recorded trace played back as a device.

PATH is any file replay.load_trace reads (native, EyeLink ASC, GazeBaseVR, Pupil Player, hmdrt CSV),
relative to the working directory (replay://traces/a.jsonl) or absolute (replay:///data/a.jsonl).
Samples are released when the driver's clock reaches their scheduled time (replay.player), so the
trace plays in real time on the host clock, at a speed factor, as fast as possible (speed=0), or in
lock-step with a virtual clock the compositor injects. Gaze and pose samples both replay. At the end
of a trace without loop, read() returns no samples (after waiting out its timeout) and the state is
"ended".

With tracker= (or any tracker_* option: drivers.tracked) the trace's gaze is taken for the true gaze and the
driver plays what that tracker model reports of it instead, worked out once when the trace is loaded: with loop,
every lap replays the same reports, as it replays the same gaze.
"""

from __future__ import annotations

from pathlib import Path

from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers import tracked
from hmdrt.drivers.base import Driver, DriverUrl, Sample
from hmdrt.errors import ConfigError
from hmdrt.replay import load_trace
from hmdrt.replay.player import Player


class ReplayDriver(Driver):
    scheme = "replay"
    grammar = (
        "replay://PATH?speed=FACTOR&loop=0|1&skip=SEC&use_source_ts=0|1&name=DEVICE "
        "(PATH relative, replay://traces/a.jsonl, or absolute, replay:///data/a.jsonl; "
        "defaults speed=1 (0: as fast as possible) loop=0 skip=0 use_source_ts=0 name=replay); "
        "EyeLink files also take screen_width_mm, screen_height_mm, distance_mm, Pupil Player min_confidence; "
        f"the gaze through a tracker model: {tracked.GRAMMAR}"
    )
    options = {
        "speed": (float, 1.0, 0.0, 1000.0),
        "loop": (bool, False, None, None),
        "skip": (float, 0.0, 0.0, 1e6),
        "use_source_ts": (bool, False, None, None),
        **{name: (float, None, 1.0, 100_000.0) for name in ("screen_width_mm", "screen_height_mm", "distance_mm")},
        "min_confidence": (float, None, 0.0, 1.0),
        **tracked.OPTIONS,
    }
    FORMAT_OPTIONS = ("screen_width_mm", "screen_height_mm", "distance_mm", "min_confidence")
    location_is_path = True

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        super().__init__(url, clock)
        if not self.url.location:
            raise ConfigError(f"replay:// needs a trace file; expected {self.grammar}")
        self.path = Path(self.url.location)
        self.tracked_by = tracked.TrackedBy.of(self)
        self._player: Player | None = None

    def open(self) -> None:
        reading = load_trace(self.path, **{k: self.opt[k] for k in self.FORMAT_OPTIONS if self.opt[k] is not None})
        self.counters.malformed += reading.malformed
        samples = reading.samples
        if self.tracked_by is not None:
            samples = self.tracked_by.report(samples, self.scheme, f"the trace {self.path.name}")
        o = self.opt
        self._player = Player(samples, o["speed"], o["loop"], o["skip"], o["use_source_ts"])
        self._player.start(self.clock.now_ns())
        self.state = "connected"

    def read(self, timeout_s: float) -> list[Sample]:
        deadline = self.clock.now_ns() + int(timeout_s * 1e9)
        while True:
            now = self.clock.now_ns()
            out = self._player.due(now)
            release = self._player.next_release()
            if release is None:
                self.state = "ended"
            if out or now >= deadline:
                return self.count(out)
            self.clock.sleep_until(deadline if release is None else min(release, deadline))
            if self.clock.now_ns() == now:  # a virtual clock: nothing more is due until it advances
                return self.count(out)

    def close(self) -> None:
        self.state = "closed"
