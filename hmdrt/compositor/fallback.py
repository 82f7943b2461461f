"""What a frame does when the gaze tracker goes silent (a driver killed, a cable pulled, a device that stops
answering): after stale_ms without a sample from the gaze device it keeps the last good gaze and widens the
fovea at widen_deg_per_s (up to max_widen_deg), since the eye may have moved anywhere since; after
centre_after_ms it falls back to the screen centre. The first sample that arrives ends the outage.

Each outage is counted with its length; the run report lists them (`outages`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from hmdrt.compositor.config import Fallback

LOGGED = 100  # outages listed in the report, the newest


@dataclass(frozen=True)
class GazeFallback:
    """This frame's fallback: how long the gaze device has been silent, the extra foveal radius, and whether
    the gaze is replaced by the screen centre."""

    silent_ns: int
    stale: bool
    widen_deg: float
    centre: bool


@dataclass
class Outages:
    """Outages of the gaze device, judged once per frame by the [fallback] section (a reload replaces it)."""

    config: Fallback = field(default_factory=Fallback)
    count: int = 0
    recovered: int = 0
    widened_frames: int = 0
    centre_frames: int = 0
    total_ns: int = 0
    longest_ns: int = 0
    _since_ns: int | None = None  # when the current outage began (the last sample's arrival)
    _log: deque = field(default_factory=lambda: deque(maxlen=LOGGED))

    def judge(self, last_received_ns: int | None, now_ns: int) -> GazeFallback:
        """The fallback for a frame at now_ns, the gaze device's last sample having arrived at last_received_ns
        (None: no sample yet, which is not an outage: there is no gaze to lose)."""
        if last_received_ns is None:
            return GazeFallback(0, False, 0.0, False)
        c = self.config
        silent = max(now_ns - last_received_ns, 0)
        if silent <= c.stale_ms * 1e6:
            if self._since_ns is not None:
                self._end(last_received_ns)
            return GazeFallback(silent, False, 0.0, False)
        if self._since_ns is None:
            self._since_ns = last_received_ns
            self.count += 1
        widen = min((silent / 1e9 - c.stale_ms / 1e3) * c.widen_deg_per_s, c.max_widen_deg)
        centre = silent > c.centre_after_ms * 1e6
        self.widened_frames += widen > 0.0
        self.centre_frames += centre
        return GazeFallback(silent, True, widen, centre)

    def _end(self, resumed_ns: int) -> None:
        length = resumed_ns - self._since_ns
        self.recovered += 1
        self.total_ns += length
        self.longest_ns = max(self.longest_ns, length)
        self._log.append({"since_ns": self._since_ns, "resumed_ns": resumed_ns, "seconds": round(length / 1e9, 3)})
        self._since_ns = None

    def to_dict(self) -> dict:
        return {
            "count": self.count,
            "recovered": self.recovered,
            "ongoing": self._since_ns is not None,
            "total_s": round(self.total_ns / 1e9, 3),
            "longest_s": round(self.longest_ns / 1e9, 3),
            "widened_frames": self.widened_frames,
            "centre_frames": self.centre_frames,
            "stale_ms": self.config.stale_ms,
            "outages": list(self._log),
        }
