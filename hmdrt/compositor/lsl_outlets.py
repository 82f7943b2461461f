"""[lsl] outlets: what the subject saw, on Lab Streaming Layer, so that LabRecorder records it beside EEG.

"frames" (type Markers, one string channel): every VSync's record as a JSON marker, {"frame_id", "vsync", "shown"
(new, late or repeat), "missed", "method"}, as JSON-encoded markers go over LSL (labstreaminglayer/PicoNeo2Eye,
README.md "Streaming Gaze Events" @ bac9805). "samples" (type FrameSamples, SAMPLE_CHANNELS): each rendered frame once,
when first shown, with the gaze (each eye's unit direction in the head frame, as rendered) and head pose it was
rendered for, the capture times of the samples they came from, how far each was predicted, whether it was held through
a blink or lost tracking, and gaze- and pose-to-photon latency; its channels carry XDF meta-data (label, eye, type,
unit). Both stamp a sample with its photon time: the VSync it was presented at, where the run report's latencies end,
on the LSL clock (hmdrt.bus.lsl.ClockMap: the host clock where they are one; in virtual time the virtual clock,
offset to LSL time at the start).

The outlets are fed through a short queue by the display thread and pushed from a thread of their own
(hmdrt.files.background): in real time a full queue drops the record and counts it, so LSL never holds up a frame;
in virtual time the display waits, so every frame is pushed.
"""

from __future__ import annotations

import json
import os
from typing import Literal

from hmdrt.bus.lsl import ClockMap, load_pylsl
from hmdrt.clock import Clock
from hmdrt.compositor.sinks import Shown, Sink
from hmdrt.errors import HmdrtError
from hmdrt.files.background import BackgroundWriter
from hmdrt.telemetry.report import FrameRecord, SampleUse

QUEUE = 256  # records waiting to be pushed; in real time more are dropped and counted
NAN = float("nan")
Outlet = Literal["frames", "samples"]
# (label, eye, type, unit) of each channel of the "samples" stream, after the XDF Gaze and MoCap meta-data
SAMPLE_CHANNELS = (
    ("frame_id", "both", "FrameNumber", "count"),
    ("vsync", "both", "FrameNumber", "count"),
    *((f"gaze_left_{a}", "left", f"Direction{a.upper()}", "normalized") for a in "xyz"),
    *((f"gaze_right_{a}", "right", f"Direction{a.upper()}", "normalized") for a in "xyz"),
    ("gaze_capture_time", "both", "TimeStamp", "s"),
    ("gaze_predicted_ms", "both", "Latency", "ms"),
    ("gaze_held", "both", "Flag", "bool"),
    ("gaze_to_photon_ms", "both", "Latency", "ms"),
    *((f"head_position_{a}", "both", f"Head{a.upper()}", "m") for a in "xyz"),
    *((f"head_orientation_{a}", "both", f"Orientation{a.upper()}", "quaternion") for a in "wxyz"),
    ("pose_capture_time", "both", "TimeStamp", "s"),
    ("pose_predicted_ms", "both", "Latency", "ms"),
    ("pose_held", "both", "Flag", "bool"),
    ("pose_to_photon_ms", "both", "Latency", "ms"),
    ("missed", "both", "Flag", "bool"),
)
Item = tuple[FrameRecord, dict | None, tuple | None]


class LslOutlets(BackgroundWriter[Item], Sink):
    """The configured outlets, created at once (ConfigError without pylsl), and the thread that pushes to them: a
    sink of the compositor (hmdrt.compositor.sinks) whose outlets outlast the run, since inlets may still be reading
    what they sent, until the compositor closes."""

    def __init__(self, outlets: list[Outlet], clock: Clock, block: bool = False):
        super().__init__("lsl-outlets", QUEUE, block)
        lsl = load_pylsl()
        self._map = ClockMap.measure(clock)
        self.source_ids = {kind: f"hmdrt-{kind}-{os.getpid()}" for kind in outlets}
        self._frames = self._samples = None
        if "frames" in outlets:
            frames_id = self.source_ids["frames"]
            info = lsl.StreamInfo("hmdrt frames", "Markers", 1, lsl.IRREGULAR_RATE, lsl.cf_string, frames_id)
            info.desc().append_child("channels").append_child("channel").append_child_value("label", "frame")
            self._frames = lsl.StreamOutlet(info)
        if "samples" in outlets:
            samples_id, count = self.source_ids["samples"], len(SAMPLE_CHANNELS)
            info = lsl.StreamInfo(
                "hmdrt samples", "FrameSamples", count, lsl.IRREGULAR_RATE, lsl.cf_double64, samples_id
            )
            channels = info.desc().append_child("channels")
            for values in SAMPLE_CHANNELS:
                channel = channels.append_child("channel")
                for key, value in zip(("label", "eye", "type", "unit"), values, strict=True):
                    channel.append_child_value(key, value)
            self._samples = lsl.StreamOutlet(info)

    def offer(self, shown: Shown) -> None:
        """Queue a shown VSync's record with the gaze and head pose its frame was rendered for (display thread)."""
        self._put((shown.record, shown.frame.gaze_dirs, shown.frame.head_pose))

    def report(self) -> dict:
        return {"lsl_not_pushed": self.lost}

    def _write(self, item: Item) -> None:
        record, gaze, pose = item
        photon = self._map.to_lsl(record.actual_present_ns)
        try:
            if self._frames is not None:
                self._frames.push_sample([self.marker(record)], photon)
            if self._samples is not None and record.shown != "repeat":
                self._samples.push_sample(self.values(record, gaze, pose), photon)
        except (RuntimeError, ValueError) as exc:  # pylsl's errors are RuntimeErrors
            raise HmdrtError(f"LSL outlet: {exc}") from None

    @staticmethod
    def marker(record: FrameRecord) -> str:
        """A VSync's "frames" marker."""
        shown = {"frame_id": record.frame_id, "vsync": record.vsync, "shown": record.shown, "missed": record.missed}
        return json.dumps({**shown, "method": record.method})

    def values(self, record: FrameRecord, gaze: dict | None, pose: tuple | None) -> list[float]:
        """A rendered frame's "samples" values, in SAMPLE_CHANNELS's order (NaN where it had no gaze or pose)."""
        directions = [float(v) for eye in ("left", "right") for v in gaze[eye]] if gaze else [NAN] * 6
        head = [float(v) for part in pose for v in part] if pose else [NAN] * 7
        return [
            float(record.frame_id),
            float(record.vsync),
            *directions,
            *self._use(record.gaze),
            _ms(record.gaze_to_photon_ms()),
            *head,
            *self._use(record.pose),
            _ms(record.pose_to_photon_ms()),
            float(record.missed),
        ]

    def _use(self, use: SampleUse | None) -> list[float]:
        """A sample's capture time on the LSL clock, its prediction in ms and whether it was held."""
        if use is None:
            return [NAN] * 3
        return [self._map.to_lsl(use.t_host), use.predicted_ns / 1e6, float(use.held)]

    def close(self) -> None:
        """Push what is queued, then destroy the outlets (their streams end for every inlet)."""
        super().close()
        self._frames = self._samples = None


def _ms(value: float | None) -> float:
    return NAN if value is None else float(value)
