"""Per-VSync frame records and the run report of `hmdrt run` (docs/architecture.md, "Run report").

Each VSync the display shows something: a new frame (on time or late) or the last one again,
timewarped to the newest head pose. A record carries Monado's per-frame metrics (predicted wake,
present and display; actual wake, render start and end, actual present; margin; missed) plus what
hmdrt adds: the method's parameters, stage times and rays, and the gaze and pose samples used with
their capture times, so gaze-to-photon = present - capture of the gaze sample shown. VSyncs whose
gaze was held through a blink (or pose through lost tracking) are counted apart, not as latency: no
newer sample existed to be late about. A record also carries the gaze errors at photon time of earlier
VSyncs that the samples arrived since have settled (hmdrt.compositor.gaze_error, which keeps their report).
The report keeps times in bounded histograms (hmdrt.telemetry.histogram), so its memory and the cost of a
summary stay the same however long the daemon runs.
"""

from __future__ import annotations

import copy
from array import array
from dataclasses import dataclass, field

import msgspec

from hmdrt.bus.messages import numpy_scalar
from hmdrt.telemetry.histogram import Histogram

SHOWN = ("new", "late", "repeat")
LEVEL_STEPS = 100  # the controller's level is counted in hundredths: bounded memory, as the times


@dataclass(frozen=True)
class SampleUse:
    """A gaze or pose sample a frame used: its device, seq and capture time, how far it was predicted, and
    whether it was held through a blink or lost tracking (the newest sample said the eye or head was lost)."""

    device: str
    seq: int
    t_host: int
    predicted_ns: int = 0
    held: bool = False


@dataclass(frozen=True)
class GazeError:
    """How far, in degrees, each eye's gaze at VSync `vsync`'s photon time was from the gaze its frame was rendered
    for (None: an eye the display does not show), and the foveal radius that frame was rendered with (None: a
    method without a fovea)."""

    vsync: int
    left_deg: float | None
    right_deg: float | None
    fovea_deg: float | None


@dataclass
class FrameRecord:
    vsync: int  # index of the VSync it was shown at
    frame_id: int  # the rendered frame shown
    shown: str  # new | late | repeat
    actual_present_ns: int
    predicted_wake_ns: int
    predicted_present_ns: int
    predicted_display_ns: int
    actual_wake_ns: int
    render_start_ns: int
    render_end_ns: int
    missed: bool  # a rendered frame shown after its desired present + 0.5 ms
    gaze: SampleUse | None
    pose: SampleUse | None
    method: str = ""
    params: dict = field(default_factory=dict)
    stages_ms: dict[str, float] = field(default_factory=dict)
    rays: int = 0
    # Work measured on the wall clock, also in virtual time: the render thread's work for the frame (from
    # wake-up to the frame built, and the loop's planning and hand-over), the method's own part of it, and the
    # display's work for this VSync (latch, timewarp) up to this record
    frame_ms: float = 0.0
    render_ms: float = 0.0
    present_ms: float = 0.0
    warp_pose: SampleUse | None = None  # the pose a repeat was warped to
    warp_skipped: bool = False  # a repeat shown unwarped: the warp would not have ended before the next VSync
    level: float | None = None  # the controller's quality level the frame was rendered at (None: no controller)
    # the gaze errors at photon time first known at this VSync, of earlier VSyncs (or, in real time, this one): the
    # tracker's gaze at a photon time comes in with samples captured after it (hmdrt.compositor.gaze_error)
    gaze_errors: list[GazeError] = field(default_factory=list)

    @property
    def margin_ns(self) -> int:
        return self.predicted_present_ns - self.render_end_ns

    @property
    def overhead_ms(self) -> float:
        """The compositor's work for a new frame: everything but the method's render (for a repeat, the
        display's work is its timewarp, reported apart)."""
        return self.present_ms if self.shown == "repeat" else self.frame_ms - self.render_ms + self.present_ms

    def gaze_to_photon_ms(self) -> float | None:
        return None if self.gaze is None else (self.actual_present_ns - self.gaze.t_host) / 1e6

    def pose_to_photon_ms(self) -> float | None:
        pose = self.warp_pose or self.pose
        return None if pose is None else (self.actual_present_ns - pose.t_host) / 1e6

    def to_dict(self) -> dict:
        # msgspec rather than dataclasses.asdict, 25x slower: this runs each VSync
        out = msgspec.to_builtins(self, enc_hook=numpy_scalar)
        out.update(
            margin_ns=self.margin_ns,
            overhead_ms=self.overhead_ms,
            gaze_to_photon_ms=self.gaze_to_photon_ms(),
            pose_to_photon_ms=self.pose_to_photon_ms(),
        )
        return out


class RunReport:
    """Accumulates frame records into the run report; cheap per record, so it runs every VSync."""

    def __init__(self, vsync_hz: float, warmup_s: float = 2.0):
        self.vsync_hz = vsync_hz
        self.warmup_ns = int(warmup_s * 1e9)  # misses after this long are also counted apart
        self.settled = {"rendered": 0, "misses": 0}
        self.shown = dict.fromkeys(SHOWN, 0)
        self.misses = 0
        self.dropped = 0  # rendered frames never shown (a newer one was ready first)
        self.frame_ms = Histogram()
        self.overhead_ms = Histogram()
        self.warp_ms = Histogram()
        self.gaze_ms = Histogram()
        self.pose_ms = Histogram()
        self.warps_skipped = 0
        self.held = {"gaze": 0, "pose": 0}  # VSyncs whose sample was held through a blink or lost tracking
        self.stages_ms: dict[str, float] = {}
        self.rays = 0
        self.levels = array("q", bytes(8 * (LEVEL_STEPS + 1)))  # new frames per controller level, in hundredths
        self.first_present: int | None = None
        self.last_present: int | None = None
        self.last_frame_id = -1
        self.out_of_order = 0

    def _settled(self, t_ns: int, missed: bool) -> None:
        if self.first_present is not None and t_ns - self.first_present >= self.warmup_ns:
            self.settled["rendered"] += 1
            self.settled["misses"] += missed

    def add(self, record: FrameRecord) -> None:
        self.shown[record.shown] += 1
        if self.first_present is None:
            self.first_present = record.actual_present_ns
        self.last_present = record.actual_present_ns
        for kind, values, use, latency in (
            ("gaze", self.gaze_ms, record.gaze, record.gaze_to_photon_ms()),
            ("pose", self.pose_ms, record.warp_pose or record.pose, record.pose_to_photon_ms()),
        ):
            if use is not None and use.held:
                self.held[kind] += 1  # no new sample to be late about: not a latency of the pipeline
            elif latency is not None:
                values.add(latency)
        if record.shown == "repeat":
            if record.warp_skipped:
                self.warps_skipped += 1
            else:
                self.warp_ms.add(record.present_ms)
            return
        self.overhead_ms.add(record.overhead_ms)
        if record.frame_id <= self.last_frame_id:
            self.out_of_order += 1
        self.last_frame_id = record.frame_id
        self.misses += record.missed
        self._settled(record.actual_present_ns, record.missed)
        self.frame_ms.add(record.frame_ms)
        self.rays += record.rays
        if record.level is not None:
            self.levels[round(record.level * LEVEL_STEPS)] += 1
        for stage, ms in record.stages_ms.items():
            self.stages_ms[stage] = self.stages_ms.get(stage, 0.0) + ms

    def snapshot(self) -> RunReport:
        """A copy whose counts later records do not change: cheap to take under a lock, then summarised
        (to_dict) outside it."""
        out = copy.copy(self)
        for name in ("settled", "shown", "held", "stages_ms"):
            setattr(out, name, dict(getattr(self, name)))
        for name in ("frame_ms", "overhead_ms", "warp_ms", "gaze_ms", "pose_ms"):
            setattr(out, name, getattr(self, name).copy())
        out.levels = array("q", self.levels)
        return out

    def level_summary(self) -> dict | None:
        """How the new frames' controller levels spread over the run: the frames rendered under a controller,
        their level's p10, p50 and p90 (hundredths) and the share at 0.5 or above (None without a controller)."""
        n = sum(self.levels)
        if not n:
            return None
        ranks = {f"p{k}": max(1, -(-k * n // 100)) for k in (10, 50, 90)}
        out: dict = {"frames": n}
        seen = 0
        for step, count in enumerate(self.levels):
            seen += count
            for key, rank in ranks.items():
                if key not in out and seen >= rank:
                    out[key] = step / LEVEL_STEPS
        out["share_at_least_half"] = round(sum(self.levels[LEVEL_STEPS // 2 :]) / n, 5)
        return out

    @property
    def frames(self) -> int:
        """Rendered frames shown (on time or late)."""
        return self.shown["new"] + self.shown["late"]

    @property
    def vsyncs(self) -> int:
        return sum(self.shown.values())

    def drop(self, t_vsync: int) -> None:
        """A rendered frame a newer one overtook at t_vsync: it missed its deadline and was never shown."""
        self.dropped += 1
        self.misses += 1
        self._settled(t_vsync, True)

    def to_dict(self, **extra) -> dict:
        n = max(self.frames, 1)
        rendered = max(self.frames + self.dropped, 1)
        span_s = (self.last_present - self.first_present) / 1e9 + 1.0 / self.vsync_hz if self.vsyncs else 0.0
        return {
            "frames": self.frames,
            "vsyncs": self.vsyncs,
            "vsync_hz": self.vsync_hz,
            "presented": self.frames,
            "re_presented": self.shown["repeat"],
            "repeat_rate": round(self.shown["repeat"] / max(self.vsyncs, 1), 5),  # VSyncs without a new frame
            "late": self.shown["late"],
            "dropped": self.dropped,
            "out_of_order": self.out_of_order,
            "deadline_misses": self.misses,
            "miss_rate": round(self.misses / rendered, 5),
            "warmup_s": self.warmup_ns / 1e9,
            "miss_rate_after_warmup": round(self.settled["misses"] / max(self.settled["rendered"], 1), 5),
            "achieved_hz": round(self.frames / span_s, 3) if span_s else 0.0,
            "frame_ms": self.frame_ms.percentiles(),
            "compositor_overhead_ms": self.overhead_ms.percentiles(),
            "timewarp_ms": self.warp_ms.percentiles(),
            "timewarp_skipped": self.warps_skipped,
            "latency_ms": {
                "gaze_to_photon": self.gaze_ms.percentiles(),
                "pose_to_photon": self.pose_ms.percentiles(),
                "held_vsyncs": dict(self.held),
            },
            "stages_ms": {k: round(v / n, 3) for k, v in self.stages_ms.items()},
            "rays_per_frame": round(self.rays / n),
            "controller_level": self.level_summary(),
            **extra,
        }
