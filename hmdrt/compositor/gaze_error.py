"""Where the eye was when the light came: each eye's gaze error at photon time, the angle between the gaze a shown
frame was rendered for and the gaze the tracker reported for that VSync's photon time (its actual present plus the
present-to-display time, when the frame is seen), and how often it fell outside the frame's foveal radius.

The tracker's gaze at a photon time is known only from samples captured after it, which arrive later. So each
VSync waits in a bounded queue (its photon time, the gaze its frame was rendered for: straight ahead when it had
none, and the frame's foveal radius) until the sample store holds samples on both sides of its photon time; the
gaze there is interpolated between them as the store interpolates. Nothing is guessed: a VSync whose photon time
fell in a blink or lost tracking (the sample before it or the one after it was invalid) is counted `held`; one
with no usable sample before its photon time, one that no sample after it came for while the store keeps samples
(its history, 1 s), one pushed out of a full queue and those still waiting when the run ends are counted
`unresolved`.

A sink of the compositor (hmdrt.compositor.sinks) offered each VSync first: on the display thread it settles what
the samples arrived since allow (a store lookup for the device's newest gaze and one per VSync settled, like the
run report's own bookkeeping) and puts the errors found into that VSync's record (FrameRecord.gaze_errors), which
the `frame` telemetry and the frames log then carry. The report keeps each eye's errors in a bounded histogram
(hmdrt.telemetry.histogram), and per eye the share of resolved VSyncs whose error was over the foveal radius their
frame was rendered with (the method's first foveal knob, hmdrt.compositor.preview.foveal_radius_deg; None for a
method without one, `full`).
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from hmdrt.clock import Clock
from hmdrt.compositor.preview import foveal_radius_deg
from hmdrt.compositor.samples import GazeEstimate, SampleStore
from hmdrt.compositor.session import AHEAD
from hmdrt.compositor.sinks import Shown, Sink
from hmdrt.spatial import angle_between
from hmdrt.telemetry.histogram import Histogram
from hmdrt.telemetry.report import FrameRecord, GazeError

KEY = "gaze_error_at_photon_deg"  # the run report's key
MAX_WAITING = 1024  # VSyncs waiting for their samples (7 s at 144 Hz); an older one is pushed out, unresolved
# VSyncs settled per VSync at most: bounds the display thread's lookups, and a record's gaze_errors within a frames
# log line, when a stalled tracker's samples arrive at once (the rest are settled at the next VSyncs)
MOST_PER_VSYNC = 32


class _Waiting(NamedTuple):
    """A shown VSync whose gaze at photon time is not known yet."""

    vsync: int
    photon_ns: int
    rendered: dict[str, np.ndarray] | None  # the frame's gaze per eye (None: rendered straight ahead)
    fovea_deg: float | None
    device: str | None  # the gaze device to ask (None: the one with the newest gaze)


class GazeErrors(Sink):
    """Each eye's gaze error at photon time over the run; `gaze_device` gives [prediction] gaze_device in force
    ("": the device with the newest gaze), asked of VSyncs whose frame used no gaze sample."""

    def __init__(
        self,
        store: SampleStore,
        clock: Clock,
        eyes: tuple[str, ...],
        gaze_device: Callable[[], str],
        max_waiting: int = MAX_WAITING,
    ):
        self._store = store
        self._clock = clock
        self._eyes = eyes
        self._gaze_device = gaze_device
        self._waiting: deque[_Waiting] = deque()
        self._max_waiting = max_waiting
        self._fovea: tuple[str, dict, float | None] = ("", {}, None)  # the last method, params and their radius
        self._lock = threading.Lock()  # the counts: the display thread adds, the stats thread reports
        self._errors = {eye: Histogram() for eye in eyes}
        self._beyond = dict.fromkeys(eyes, 0)  # errors over the frame's foveal radius
        self._with_fovea = 0  # resolved VSyncs whose frame had a foveal radius
        self._counts = {"resolved": 0, "held": 0, "unresolved": 0}

    def offer(self, shown: Shown) -> None:
        """Queue this VSync and put the errors resolved by now into its record."""
        record = shown.record
        now = self._clock.now_ns()
        waiting = _Waiting(
            record.vsync,
            record.actual_present_ns + record.predicted_display_ns - record.predicted_present_ns,
            shown.frame.gaze_dirs,
            self._fovea_deg(record),
            record.gaze.device if record.gaze is not None else self._gaze_device() or None,
        )
        if len(self._waiting) >= self._max_waiting:
            self._waiting.popleft()
            self._count("unresolved")
        self._waiting.append(waiting)
        record.gaze_errors = self._resolve(now, MOST_PER_VSYNC)

    def finish(self) -> None:
        """The run has ended: what the samples now allow is resolved, and the rest counted unresolved."""
        self._resolve(self._clock.now_ns(), len(self._waiting))
        with self._lock:
            self._counts["unresolved"] += len(self._waiting)
        self._waiting.clear()

    def report(self) -> dict:
        with self._lock:
            errors = {eye: histogram.copy() for eye, histogram in self._errors.items()}
            beyond, with_fovea, counts = dict(self._beyond), self._with_fovea, dict(self._counts)
        out: dict = {}
        for eye, histogram in errors.items():
            share = round(beyond[eye] / with_fovea, 5) if with_fovea else None
            out[eye] = {**histogram.percentiles(), "beyond_fovea": share}
        return {KEY: {**out, **counts, "waiting": len(self._waiting)}}

    def _fovea_deg(self, record: FrameRecord) -> float | None:
        """The foveal radius the record's frame was rendered with, worked out again only when the method or its
        parameters changed."""
        method, params, radius = self._fovea
        if record.method != method or record.params != params:
            radius = foveal_radius_deg(record.method, record.params)
            self._fovea = (record.method, record.params, radius)
        return radius

    def _resolve(self, now: int, most: int) -> list[GazeError]:
        """The errors of the oldest waiting VSyncs, at most `most` of them, that the samples arrived by `now`
        settle, in VSync order; it stops at the first that must wait on (photon times grow with the VSync, so the
        later ones must wait too)."""
        out: list[GazeError] = []
        newest: dict[str | None, GazeEstimate | None] = {}  # per device asked: its gaze now, from what has arrived
        for _ in range(most):
            if not self._waiting or self._waiting[0].photon_ns >= now:  # none can have a sample after it yet
                break
            waiting = self._waiting[0]
            if waiting.device not in newest:
                newest[waiting.device] = self._store.gaze_at(now, now, waiting.device)
            if not self._settle(waiting, newest[waiting.device], now, out):
                break
            self._waiting.popleft()
        return out

    def _settle(self, waiting: _Waiting, newest: GazeEstimate | None, now: int, out: list[GazeError]) -> bool:
        """Whether one VSync is settled by now, its error then counted and put in `out` or it counted held or
        unresolved. It is once a sample captured at or after its photon time has arrived: a usable one, or the first
        of a blink that began after it (`newest`, the device's gaze now, says which); or once it has waited longer
        than the store keeps samples."""
        photon = waiting.photon_ns
        after = newest is not None and (
            newest.source_t_host >= photon or (newest.blinking and newest.blink_since_ns > photon)
        )
        if not after and now - photon <= self._store.history_ns:
            return False
        at = self._store.gaze_at(photon, now, waiting.device)
        if at is not None and not at.blinking and at.age_ns <= 0:  # interpolated between samples, or one at that time
            out.append(self._error(waiting, {"left": at.left, "right": at.right}))
        elif at is not None and (at.blinking or after):  # a sample on either side said the eye was closed or lost
            self._count("held")
        else:  # no usable sample before it, or none after it came while one could
            self._count("unresolved")
        return True

    def _error(self, waiting: _Waiting, seen: dict[str, np.ndarray]) -> GazeError:
        """Count and return one VSync's errors (the store's and the frames' gaze are unit vectors: finite angles)."""
        degrees = {}
        for eye in self._eyes:
            rendered = AHEAD if waiting.rendered is None else waiting.rendered[eye]
            degrees[eye] = math.degrees(angle_between(rendered.tolist(), seen[eye].tolist()))
        fovea = waiting.fovea_deg
        with self._lock:
            self._counts["resolved"] += 1
            self._with_fovea += fovea is not None
            for eye, error in degrees.items():
                self._errors[eye].add(error)
                self._beyond[eye] += fovea is not None and error > fovea
        return GazeError(waiting.vsync, degrees.get("left"), degrees.get("right"), fovea)

    def _count(self, key: str) -> None:
        with self._lock:
            self._counts[key] += 1
