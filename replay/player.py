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

import msgspec
import numpy as np

from hmdrt.errors import ConfigError
from hmdrt.replay.table import GAZE, POSE, SampleTable
from hmdrt.replay.trace import Gaze, Pose, Sample

MAX_BATCH = 4096  # samples per due() call, so a fast replay still lets its host publish status


class Player:
    """A trace's samples in time order with the options of replay:// (speed, loop, skip, use_source_ts).

    The samples stay in a SampleTable, played in the order of an index array: memory is the table's 106 bytes a
    sample and 16 more (the order and the sorted times), never an object per sample."""

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
        self.table = SampleTable.of(samples)
        times = self.table.column("t_host")
        order = np.argsort(times, kind="stable")  # stable: file order among equal times
        times = times[order]
        self.t0 = int(times[0]) + round(skip_s * 1e9)
        first = int(np.searchsorted(times, self.t0, side="left"))
        if first == len(times):
            span_s = (int(times[-1]) - int(times[0])) / 1e9
            raise ConfigError(f"skip={skip_s} s is past the end of the trace ({span_s:.3f} s long)")
        self._order, self._times = order[first:], times[first:]
        self.speed, self.loop, self.use_source_ts = speed, loop, use_source_ts
        self.lap_ns = self._lap_ns() if loop else 0
        kinds, seqs = self.table.column("kind")[self._order], self.table.column("seq")[self._order]
        self.seq_stride: dict[type, int] = {}  # per kind, added to seq on every lap
        for kind, code in ((Gaze, GAZE), (Pose, POSE)):
            if (kinds == code).any():
                self.seq_stride[kind] = int(seqs[kinds == code].max()) + 1
        self.start(0)

    def _lap_ns(self) -> int:
        times = np.unique(self._times)
        if len(times) < 2:
            raise ConfigError("loop=1 needs a trace with samples at two or more times")
        return int(times[-1]) - self.t0 + round(float(np.median(np.diff(times))))

    def start(self, now_ns: int) -> None:
        """Begin the replay at clock time now_ns."""
        self._start, self._index, self._lap = now_ns, 0, 0

    @property
    def ended(self) -> bool:
        return self._index >= len(self._order)

    def _offset(self) -> int:
        """Trace time of the next sample since t0, counting the laps played."""
        return int(self._times[self._index]) - self.t0 + self._lap * self.lap_ns

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
        stamps: list[tuple[int, int, int]] = []  # (index, lap, release) of each sample due
        while len(stamps) < MAX_BATCH and (release := self.next_release()) is not None and release <= now_ns:
            stamps.append((self._index, self._lap, release))
            self._index += 1
            if self.ended and self.loop:
                self._index, self._lap = 0, self._lap + 1
        originals = self.table.take(self._order[[index for index, _, _ in stamps]])
        out: list[Sample] = []
        for s, (_, lap, release) in zip(originals, stamps, strict=True):
            lap_ns = lap * self.lap_ns
            if self.use_source_ts:
                t_host, t_dev = s.t_host + lap_ns, s.t_dev
            else:
                t_host = self._start + s.t_host - self.t0 + lap_ns if self.speed == 0 else release
                t_dev = s.t_host if s.t_dev is None else s.t_dev
            seq = s.seq + lap * self.seq_stride[type(s)]
            out.append(msgspec.structs.replace(s, t_host=t_host, t_dev=t_dev, seq=seq))
        return out
