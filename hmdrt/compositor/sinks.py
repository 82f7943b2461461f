"""Where the shown frames go. After every VSync that showed something the display's callback offers the same Shown
(the record, the images shown and the frame they came from) to each sink in the compositor's list, in order, on the
display thread: the gaze error at photon time (hmdrt.compositor.gaze_error, first: it adds to the record the errors
that the samples arrived since have resolved, for the others to carry), the `frame` telemetry, the frames log, the
LSL outlets, the frames on disk and the preview. A sink starts with the run, finishes when the run ends, is closed
with the compositor, and puts its own counters into the run report. Adding an output is a module with a Sink and
one line that appends it to `Compositor.sinks`.

A sink must not hold up the display: one that writes or encodes hands the work to a thread of its own
(hmdrt.files.background), and in real time drops and counts what it has no room for.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Protocol

import numpy as np

from hmdrt.compositor.display import Frame
from hmdrt.compositor.endpoints import Telemetry
from hmdrt.files.background import BackgroundWriter
from hmdrt.present.output import FrameWriter
from hmdrt.telemetry.frames_log import FramesLog
from hmdrt.telemetry.report import FrameRecord

FRAME = "frame"  # the telemetry topic of every VSync's record


@dataclass
class Shown:
    """What one VSync showed: its record, the images (pooled buffers: hold them only while needed) and the frame
    they were rendered as, with the eye cameras, gaze and head pose of its render (a repeat's: the frame repeated)."""

    record: FrameRecord
    images: list[np.ndarray]
    frame: Frame

    @cached_property
    def fields(self) -> dict:
        """The record as the telemetry and the frames log carry it, made once per VSync for every sink."""
        return self.record.to_dict()


class Sink(Protocol):
    """What consumes the shown frames. A class that names Sink as its base gets these as defaults: nothing to
    start, finish or close, and nothing in the report."""

    def start(self) -> None:
        """Before the first VSync (Compositor.run)."""

    def offer(self, shown: Shown) -> None:
        """One VSync's frame, on the display thread: hand it on, do not work on it here."""

    def finish(self) -> None:
        """The run has ended: write out what is queued. What must outlast the run stays until close()."""

    def close(self) -> None:
        """Release everything; safe more than once, and also when start() was never called."""

    def report(self) -> dict:
        """This sink's counters, merged into the run report."""
        return {}


class FrameTelemetry(Sink):
    """Every VSync's record on the telemetry `frame` topic; the telemetry socket is the compositor's to close."""

    def __init__(self, telemetry: Telemetry):
        self._telemetry = telemetry

    def offer(self, shown: Shown) -> None:
        self._telemetry.publish(FRAME, shown.fields)


class _Written(Sink):
    """A background writer as a sink: it starts with the run, writes out what is queued and closes when the run
    ends, and reports what it dropped (real time) or could not write under `key`."""

    key = ""

    def __init__(self, writer: BackgroundWriter):
        self.writer = writer

    def start(self) -> None:
        self.writer.start()

    def finish(self) -> None:
        self.writer.close()

    def close(self) -> None:
        self.writer.close()

    def report(self) -> dict:
        return {self.key: self.writer.lost}


class LoggedFrames(_Written):
    """Every VSync's record as a line of the frames log ([output] frames_log)."""

    key = "frames_log_not_written"
    writer: FramesLog

    def offer(self, shown: Shown) -> None:
        self.writer.offer(shown.fields)


class WrittenFrames(_Written):
    """Every `every`th VSync's images as a PNG and/or a video frame ([output] frames_dir, video)."""

    key = "frames_not_written"
    writer: FrameWriter

    def offer(self, shown: Shown) -> None:
        self.writer.offer(shown.record.vsync, shown.images)
