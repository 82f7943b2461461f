"""One frame's work on the render thread, from its wake-up to the Frame handed to the display: gaze and head pose
predicted for the frame's display time from what has arrived (hmdrt.compositor.samples), with the fallback for a
silent gaze tracker (hmdrt.compositor.fallback); a step of the budget controller on the frames shown or dropped since
the last (hmdrt.compositor.controller), and its foresight of this one (a probe of the fovea where the gaze is about to
be, hmdrt.compositor.foresight); and the method's render (hmdrt.compositor.session). Also what a repeated frame is
warped to: the eye cameras at the head pose predicted for its VSync.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

from hmdrt.clock import Clock
from hmdrt.compositor.config import RunConfig
from hmdrt.compositor.controller import BudgetController
from hmdrt.compositor.display import Frame
from hmdrt.compositor.fallback import Outages
from hmdrt.compositor.foresight import FovealProbe
from hmdrt.compositor.pacer import FrameTiming, Pacer
from hmdrt.compositor.samples import GazeEstimate, PoseEstimate, SampleStore
from hmdrt.compositor.session import Session
from hmdrt.optics import EyeCamera
from hmdrt.telemetry.report import SampleUse
from hmdrt.telemetry.stats import FrameStats


def sample_use(estimate: GazeEstimate | PoseEstimate | None) -> SampleUse | None:
    """What a frame record says of the sample an estimate came from: its device, sequence number and capture time,
    how far it was predicted, and whether it was held through a blink or lost tracking."""
    if estimate is None:
        return None
    held = estimate.blinking if isinstance(estimate, GazeEstimate) else estimate.tracking_lost
    return SampleUse(estimate.device, estimate.source_seq, estimate.source_t_host, estimate.predicted_ns, held)


@dataclass(eq=False)
class FrameBuilder:
    """Builds the frames; `config` and `controller` are the compositor's to set (at start and on a reload), and
    `presents` takes (frame id, frame ms, missed, rays) of each frame shown new or dropped, from the display thread."""

    config: RunConfig
    session: Session
    store: SampleStore
    outages: Outages
    clock: Clock
    pacer: Pacer
    controller: BudgetController | None = None
    presents: deque[tuple[int, float, bool, int]] = field(default_factory=deque)
    probe: FovealProbe = field(init=False)

    def __post_init__(self) -> None:
        self.probe = FovealProbe(self.session.tracer)

    def estimates(self, t_display: int, now: int) -> tuple[GazeEstimate | None, PoseEstimate | None, float]:
        """Gaze and pose for the display time, and the fallback's foveal widening in degrees: while the gaze
        device is silent, the fallback's gaze (the last good one, widened by the controller, then none: the
        screen centre)."""
        p = self.config.prediction
        gaze = self.store.gaze_at(t_display, now, p.gaze_device or None)
        pose = self.store.pose_at(t_display, now, p.pose_device or None)
        device = p.gaze_device or (gaze.device if gaze is not None else None)
        fallback = self.outages.judge(self.store.last_received(device) if device else None, now)
        return (None if fallback.centre else gaze), pose, fallback.widen_deg

    def warp_target(self, t_vsync: int) -> tuple[dict[str, EyeCamera], SampleUse] | None:
        """The eye cameras at the head pose predicted for a repeated frame's display time (the display thread's)."""
        pose = self.store.pose_at(t_vsync + self.pacer.present_to_display_ns, t_vsync, None)
        if pose is None:
            return None
        return self.session.cameras_for(pose), sample_use(pose)

    def build(self, timing: FrameTiming, woke: int, loop_ns: int = 0) -> Frame:
        """One frame's work from its wake-up: estimates, the controller's step, the method's render; its
        frame_ms adds loop_ns, the render loop's own work for it (planning, and handing over the frame before)."""
        t0 = time.perf_counter_ns()
        gaze, pose, widen_deg = self.estimates(timing.predicted_display_ns, woke)
        self.tune(None if gaze is None else gaze.speed_deg_s, widen_deg)
        stats = FrameStats()
        cameras = self.session.cameras_for(pose)
        if self.controller is not None and self.controller.foresees:
            with stats.stage("foresight"):
                fore = self.probe.read(cameras, self.session.directions(gaze)[0], self.controller.fovea_deg)
                self.controller.anticipate(timing.frame_id, fore)
        start = self.clock.now_ns()
        delay = int(self.config.pacing.render_delay_ms * 1e6)
        images, cameras, render_ns = self.session.render(
            timing.frame_id, gaze, pose, self.config.run.seed, stats, delay, cameras
        )
        end = self.clock.now_ns()
        frame = Frame(
            timing=timing,
            images=images,
            cameras=cameras,
            actual_wake_ns=woke,
            render_start_ns=start,
            render_end_ns=end,
            gaze=sample_use(gaze),
            gaze_dirs=None if gaze is None else {"left": gaze.left, "right": gaze.right},
            head_pose=None if pose is None else (pose.position, pose.orientation),
            pose=sample_use(pose),
            method=self.session.method.name,
            params=self.session.params(),
            stages_ms=dict(stats.stages_ms),
            rays=sum(stats.rays.values()),
            frame_ms=0.0,
            render_ms=render_ns / 1e6,
            level=None if self.controller is None else self.controller.level,
        )
        frame.frame_ms = (loop_ns + time.perf_counter_ns() - t0) / 1e6
        return frame

    def tune(self, gaze_speed_deg_s: float | None, widen_deg: float) -> None:
        """Feed the controller the frames shown or dropped since the last call: their work on the wall clock
        (also in virtual time) against one period less the margin, the budget of the display's own rate; it
        widens the fovea for the gaze speed of the frame about to be rendered and the fallback's widen_deg."""
        while self.presents:  # only the render thread takes from it: not empty stays not empty
            frame_id, frame_ms, missed, rays = self.presents.popleft()
            if self.controller is None:
                continue
            self.controller.update(
                frame_id,
                int(frame_ms * 1e6),
                self.session.profile.period_ns - self.pacer.margin_ns,
                missed,
                gaze_speed_deg_s,
                widen_deg,
                rays,
            )
