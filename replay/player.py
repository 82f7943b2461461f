"""The schedule of a trace's replay on a clock: which samples are due when, and how they are stamped.

After start(now), sample i is released at now + (t_i - t0) / speed, where t0 is the trace's first
time plus the skip; speed 0 releases everything at once. Released samples carry their release time
as t_host (speed 0: the trace's spacing from the start) and their original device time as t_dev
(the trace time when the file has none); use_source_ts keeps t_host and t_dev exactly as recorded,
so recording a replay reproduces the trace. With loop, each lap follows the last after one sample
period (the median gap between distinct times), and t_host and seq keep increasing across laps.
"""

from __future__ import annotations

from collections.abc import Sequence
from itertools import pairwise
from statistics import median

import msgspec

from hmdrt.errors import ConfigError
from hmdrt.replay.trace import Sample

MAX_BATCH = 4096  # samples per due() call, so a fast replay still lets its host publish status


class Player:
    """A trace's samples in time order with the options of replay:// (speed, loop, skip, use_source_ts)."""

    def __init__(
        self,
        samples: Sequence[Sample],
        speed: float = 1.0,
        loop: bool = False,
        skip_s: float = 0.0,
        use_source_ts: bool = False,
    ):
        if not samples:
            raise ConfigError("the trace holds no samples to replay")
        ordered = sorted(samples, key=lambda s: s.t_host)  # stable: file order among equal times
        self.t0 = ordered[0].t_host + round(skip_s * 1e9)
        self.samples = [s for s in ordered if s.t_host >= self.t0]
        if not self.samples:
            span_s = (ordered[-1].t_host - ordered[0].t_host) / 1e9
            raise ConfigError(f"skip={skip_s} s is past the end of the trace ({span_s:.3f} s long)")
        self.speed, self.loop, self.use_source_ts = speed, loop, use_source_ts
        self.lap_ns = self._lap_ns() if loop else 0
        self.seq_stride: dict[type, int] = {}  # per kind, added to seq on every lap
        for s in self.samples:
            self.seq_stride[type(s)] = max(self.seq_stride.get(type(s), 0), s.seq + 1)
        self.start(0)

    def _lap_ns(self) -> int:
        times = sorted({s.t_host for s in self.samples})
        if len(times) < 2:
            raise ConfigError("loop=1 needs a trace with samples at two or more times")
        return times[-1] - self.t0 + round(median(b - a for a, b in pairwise(times)))

    def start(self, now_ns: int) -> None:
        """Begin the replay at clock time now_ns."""
        self._start, self._index, self._lap = now_ns, 0, 0

    @property
    def ended(self) -> bool:
        return self._index >= len(self.samples)

    def _offset(self) -> int:
        """Trace time of the next sample since t0, counting the laps played."""
        return self.samples[self._index].t_host - self.t0 + self._lap * self.lap_ns

    def next_release(self) -> int | None:
        """Clock time at which the next sample is due; None once the replay has ended."""
        if self.ended:
            return None
        if self.speed == 0:
            return self._start
        offset = self._offset()
        return self._start + (offset if self.speed == 1 else round(offset / self.speed))

    def due(self, now_ns: int) -> list[Sample]:
        """The samples due by clock time now_ns (at most MAX_BATCH), stamped for publishing."""
        out: list[Sample] = []
        while len(out) < MAX_BATCH and (release := self.next_release()) is not None and release <= now_ns:
            s = self.samples[self._index]
            lap_ns = self._lap * self.lap_ns
            if self.use_source_ts:
                t_host, t_dev = s.t_host + lap_ns, s.t_dev
            else:
                t_host = self._start + self._offset() if self.speed == 0 else release
                t_dev = s.t_host if s.t_dev is None else s.t_dev
            seq = s.seq + self._lap * self.seq_stride[type(s)]
            out.append(msgspec.structs.replace(s, t_host=t_host, t_dev=t_dev, seq=seq))
            self._index += 1
            if self.ended and self.loop:
                self._index, self._lap = 0, self._lap + 1
        return out
