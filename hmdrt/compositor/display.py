"""The simulated display: at each VSync it latches the newest rendered frame that is finished and due,
or shows the last one again, rotated to the newest head pose (rotational timewarp).

Rules (Monado's compositor; OpenXR xrEndFrame): a frame is never shown before the VSync it targets,
never after a newer one (frames stay in order; an older finished frame that a newer one overtakes is
dropped and counted), and it is a miss when it is shown later than its desired present + 0.5 ms. A
repeat is warped from the frame as rendered, not from an earlier warp, so errors do not accumulate.
Latching depends only on timestamps: a frame counts as finished when it is handed over (submit stamps its
render end under the display's lock), so a frame stamped before a VSync is always there when that VSync is
latched, and the display thread's own wake-up jitter never changes what was shown when. Images are shown as
rendered, without a copy; warps go into pooled buffers (hmdrt.compositor.buffers).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hmdrt.clock import Clock
from hmdrt.compositor.buffers import BufferPool
from hmdrt.compositor.clock import VsyncClock
from hmdrt.compositor.pacer import FrameTiming
from hmdrt.optics import EyeCamera
from hmdrt.present.timewarp import timewarp
from hmdrt.telemetry.report import FrameRecord, SampleUse

MISS_NS = 500_000  # Monado: a present later than desired by more than this is a miss
WARP_RETRY_DECAY = 0.98  # each skipped warp shrinks the warp estimate, so a warp is tried again now and then


@dataclass
class Frame:
    """A rendered frame on its way to the display."""

    timing: FrameTiming
    images: list[np.ndarray]  # per eye, linear RGB, as rendered: pooled buffers, never written while held
    cameras: dict[str, EyeCamera]
    actual_wake_ns: int
    render_start_ns: int
    render_end_ns: int
    gaze: SampleUse | None
    pose: SampleUse | None
    method: str
    params: dict
    stages_ms: dict[str, float]
    rays: int
    frame_ms: float  # the render thread's wall-clock work for it: from wake-up to built, its planning and hand-over
    render_ms: float  # the method's part of it
    level: float | None = None  # the controller's quality level it was rendered at (None: no controller)
    gaze_dirs: dict[str, np.ndarray] | None = None  # each eye's unit gaze (head frame) it was rendered for; None: ahead
    head_pose: tuple[np.ndarray, np.ndarray] | None = None  # head position (m), orientation (w, x, y, z); None: start


# (vsync time) -> the eye cameras at the newest head pose for that VSync, and the pose sample used
WarpTarget = Callable[[int], tuple[dict[str, EyeCamera], SampleUse] | None]
# (record, images shown) after every VSync that showed something
Shown = Callable[[FrameRecord, list[np.ndarray]], None]
# (frame, vsync time) for a finished frame that a newer one overtook: a missed deadline, never shown
Dropped = Callable[[Frame, int], None]


class Display:
    def __init__(
        self,
        vsync: VsyncClock,
        clock: Clock,
        warp_target: WarpTarget,
        on_shown: Shown,
        on_dropped: Dropped,
        warp_deadline: bool = False,
        warp_pools: dict[str, BufferPool] | None = None,
    ):
        """With warp_deadline, a repeat is warped only when the warp (its filtered wall time) would end before
        the next VSync; otherwise what was shown last is shown again and counted (warps_skipped), so that at
        a resolution where one warp takes longer than a period the display does not starve the renderer.
        warp_pools: per eye, the pools the warped images come from (made on the first warp where not given)."""
        self.vsync = vsync
        self.clock = clock
        self._warp_target = warp_target
        self._on_shown = on_shown
        self._on_dropped = on_dropped
        self._warp_deadline = warp_deadline
        self._lock = threading.Lock()
        self._pending: list[Frame] = []
        self.last: Frame | None = None  # the newest frame shown
        self._shown: tuple[list[np.ndarray], SampleUse | None] = ([], None)  # the images shown last, and their pose
        self._warp_ns = 0.0  # filtered wall time of one warp of all eyes
        self.warp_pools: dict[str, BufferPool] = warp_pools or {}  # per eye: the warped images' buffers
        self.dropped = 0
        self.warps_skipped = 0

    def submit(self, frame: Frame) -> None:
        """Hand over a rendered frame; its render_end_ns becomes now."""
        with self._lock:
            frame.render_end_ns = self.clock.now_ns()
            self._pending.append(frame)

    @property
    def backlog(self) -> int:
        """Frames handed over and not yet shown or dropped."""
        with self._lock:
            return len(self._pending)

    def _due(self, t_vsync: int) -> Frame | None:
        """The newest pending frame finished by t_vsync and targeting it or earlier; older due ones are dropped."""
        with self._lock:
            due = [f for f in self._pending if f.render_end_ns <= t_vsync and f.timing.desired_present_ns <= t_vsync]
            if not due:
                return None
            newest = max(due, key=lambda f: f.timing.frame_id)
            self._pending = [f for f in self._pending if f.timing.frame_id > newest.timing.frame_id]
        for frame in due:
            if frame is not newest:
                self.dropped += 1
                self._on_dropped(frame, t_vsync)
        return newest

    def latch(self, index: int) -> FrameRecord | None:
        """What VSync `index` shows; None before the first frame."""
        start = time.perf_counter_ns()
        t = self.vsync.vsync(index)
        frame = self._due(t)
        if frame is not None:
            late = t > frame.timing.desired_present_ns + MISS_NS
            self.last = frame
            self._shown = (frame.images, None)
            record = self._record(index, t, frame, "late" if late else "new", late)
            record.present_ms = (time.perf_counter_ns() - start) / 1e6
            self._on_shown(record, frame.images)
            return record
        if self.last is None:
            return None
        target = self._warp_target(t)
        record = self._record(index, t, self.last, "repeat", False)
        if target is not None and self._warp_fits(t):
            cameras, warp_pose = target
            rendered = self.last.cameras
            images = [
                timewarp(image, rendered[eye], cameras[eye], self._warp_buffer(eye, image.shape)).image
                for eye, image in zip(rendered, self.last.images, strict=True)
            ]
            self._shown = (images, warp_pose)
            took = time.perf_counter_ns() - start
            self._warp_ns = took if not self._warp_ns else 0.8 * self._warp_ns + 0.2 * took
        elif target is not None:
            self.warps_skipped += 1
            record.warp_skipped = True
            self._warp_ns *= WARP_RETRY_DECAY
        images, record.warp_pose = self._shown
        record.present_ms = (time.perf_counter_ns() - start) / 1e6
        self._on_shown(record, images)
        return record

    def _warp_buffer(self, eye: str, shape: tuple[int, ...]) -> np.ndarray:
        pool = self.warp_pools.get(eye)
        if pool is None or pool.shape != shape:
            pool = self.warp_pools[eye] = BufferPool(shape)
        return pool.take()

    def _warp_fits(self, t_vsync: int) -> bool:
        return not self._warp_deadline or self.clock.now_ns() + self._warp_ns <= t_vsync + self.vsync.period_ns

    @staticmethod
    def _record(index: int, t: int, frame: Frame, shown: str, missed: bool) -> FrameRecord:
        timing = frame.timing
        return FrameRecord(
            vsync=index,
            frame_id=timing.frame_id,
            shown=shown,
            actual_present_ns=t,
            predicted_wake_ns=timing.wake_ns,
            predicted_present_ns=timing.desired_present_ns,
            predicted_display_ns=timing.predicted_display_ns,
            actual_wake_ns=frame.actual_wake_ns,
            render_start_ns=frame.render_start_ns,
            render_end_ns=frame.render_end_ns,
            missed=missed,
            gaze=frame.gaze,
            pose=frame.pose,
            method=frame.method,
            params=frame.params,
            stages_ms=frame.stages_ms if shown != "repeat" else {},
            rays=frame.rays if shown != "repeat" else 0,
            frame_ms=frame.frame_ms if shown != "repeat" else 0.0,
            render_ms=frame.render_ms if shown != "repeat" else 0.0,
            level=frame.level,
        )
