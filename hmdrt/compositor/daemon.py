"""`hmdrt run CONFIG.toml`: the compositor daemon.

Each frame, as a compositor pacer schedules it (Monado's u_pacing; hmdrt.compositor.pacer): wake at
the predicted time, sample gaze and head pose predicted for the frame's display time from what has
arrived, render through the method, and hand the frame to the display, which latches it at its VSync
or, when it is late, shows the last frame again timewarped to the newest head pose. Telemetry goes
out per VSync (`frame`) and each second (`stats`), and previews of the shown frames (`preview`,
hmdrt.compositor.preview) while a client subscribes to them; the run report is written at the end, also after
SIGTERM. In real time the render loop and the display run on their own threads against the host
clock; with virtual_time the clock moves one period per frame, drivers are polled against it, and
runs reproduce bit for bit. The control socket's commands are hmdrt.compositor.control's, the frames on disk
hmdrt.present.output's, and what a reload may change hmdrt.compositor.config.reload_plan's.
"""

from __future__ import annotations

import gc
import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from contextlib import contextmanager
from functools import partial

import msgspec
import numba
import numpy as np
import zmq

from hmdrt.bus.local import bind_endpoint
from hmdrt.bus.security import Guard, ServerKeys, check_binds
from hmdrt.clock import MONOTONIC, Clock, VirtualClock
from hmdrt.compositor import control
from hmdrt.compositor.buffers import counts
from hmdrt.compositor.clock import VsyncClock
from hmdrt.compositor.config import RunConfig, load_config, reload_plan
from hmdrt.compositor.control import MUTATING
from hmdrt.compositor.controller import BudgetController, ControllerConfig
from hmdrt.compositor.display import Display, Frame
from hmdrt.compositor.endpoints import ControlServer, Ingest, Telemetry
from hmdrt.compositor.fallback import Outages
from hmdrt.compositor.lsl_outlets import LslOutlets
from hmdrt.compositor.pacer import FrameTiming, Pacer
from hmdrt.compositor.preview import PREVIEW, PreviewPublisher
from hmdrt.compositor.samples import GazeEstimate, PoseEstimate, SampleStore
from hmdrt.compositor.session import Session
from hmdrt.compositor.sources import Sources
from hmdrt.console.logs import TelemetryHandler
from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.files.background import BackgroundWriter
from hmdrt.foveation import MethodChoice
from hmdrt.optics import EyeCamera
from hmdrt.present.output import FrameWriter, check_folder
from hmdrt.telemetry.frames_log import FramesHeader, FramesLog
from hmdrt.telemetry.report import FrameRecord, RunReport, SampleUse
from hmdrt.telemetry.stats import FrameStats
from hmdrt.version import __version__
from hmdrt.views import compose_pose, eye_cameras

log = logging.getLogger(__name__)

FIRST_PRESENT_NS = 50_000_000  # Monado's fake pacer: the first present is assumed 50 ms out
CONNECT_WAIT_S = 3.0  # how long the start waits for its drivers to connect (a device may come later)
MAX_AHEAD = 4  # frames the renderer may hand over before the display has shown them (the pacer remembers 16)
# A thread waiting for the GIL gets it within this (Python's default is 5 ms, a sixth of a 30 Hz frame): the
# display and the hand-over of a finished frame must not wait behind the ingest or a driver for that long.
SWITCH_INTERVAL_S = 0.0005


class Compositor:
    def __init__(self, config: RunConfig, clock: Clock | None = None, context: zmq.Context | None = None):
        self.config = config
        virtual = config.run.virtual_time
        self.clock = clock or (VirtualClock(0) if virtual else MONOTONIC)
        self._paced = not virtual  # virtual time schedules each frame over the period before its VSync
        # loopback only, or CURVE with [security]: checked, and the keys read, before any start-up work
        security = config.security
        check_binds({f"bus.{k}": v for k, v in msgspec.structs.asdict(config.bus).items()}, security is not None)
        self._server_keys = ServerKeys.load(security.server_key, security.allowed_clients) if security else None
        self._control_endpoint = bind_endpoint(config.bus.control)  # by default in a folder of this user's only
        self._kernel_threads = self._kernel_thread_count(config)
        self.session = Session(config)
        self.store = SampleStore(horizon_ns=int(config.prediction.horizon_ms * 1e6))
        self.report = RunReport(self.session.profile.refresh_hz, config.run.warmup_s)
        self.controller = self._make_controller()
        self.outages = Outages(config.fallback)
        self._lock = threading.Lock()  # pacer and report: the render and display threads share them
        self._pending: list[tuple[str, object]] = []  # control changes applied between frames
        # (frame id, frame ms, missed) for the controller: appended by the display thread, taken by the render thread
        self._presents: deque[tuple[int, float, bool]] = deque()
        self.writer: FrameWriter | None = None
        self.frames_log: FramesLog | None = None
        self.lsl: LslOutlets | None = None
        self.shown_images: list[np.ndarray] | None = None
        self.snapshots_refused = 0  # snapshot names that led out of the snapshot folder or to an existing file
        self.stop = threading.Event()
        self._context = context or zmq.Context.instance()
        try:
            if config.output.frames_log:  # opened before the start-up's work: a path it cannot write fails at once
                self.frames_log = FramesLog(config.output.frames_log, self._frames_header(), block=virtual)
            if config.lsl.outlets:  # likewise: without pylsl it fails at once
                self.lsl = LslOutlets(config.lsl.outlets, self.clock, block=virtual)
            self.guard = Guard(self._context, self._server_keys) if self._server_keys else None  # before any bind
            self.telemetry = Telemetry(self._context, config.bus.telemetry, self.guard, on_demand=(PREVIEW,))
            self.preview = PreviewPublisher(self.telemetry)
            self._log = TelemetryHandler(self.telemetry.publish)
            self._log.attach()
            self.ingest = Ingest(self._context, config.bus.ingest, self.store.add, self.clock, self.guard)
            self.sources = Sources(
                [d.url for d in config.drivers],
                self.clock,
                virtual,
                self.ingest.address,
                self.store.add,
                keys=self.guard.own_keys if self.guard else None,
            )
            # compiled kernels, allocated buffers and connected drivers before the VSync clock starts
            self.session.warm_up()
            self.sources.wait_connected(CONNECT_WAIT_S)
            # and no collection of what start-up built: a full one scanned its ~180k objects, stopping every
            # thread for ~120 ms (four frames at 30 Hz) whenever it came; frozen, it takes microseconds
            gc.collect()
            gc.freeze()
            self.vsync = VsyncClock(self.session.profile.period_ns, self.clock.now_ns() + FIRST_PRESENT_NS)
            self.pacer = Pacer(self.vsync, **self._pacing(config))
            out = config.output
            self.writer = FrameWriter(
                out.frames_dir, out.video, out.every, self.session.profile.refresh_hz, block=virtual
            )
            self.display = Display(
                self.vsync,
                self.clock,
                self._warp_target,
                self._shown,
                self._dropped,
                warp_deadline=not virtual,
                warp_pools=self.session.warp_pools,
            )
            self.control = ControlServer(
                self._context, self._control_endpoint, partial(control.handle, self), MUTATING, self.guard
            )
        except (HmdrtError, ValueError):
            self.close()
            raise
        self._started_ns = self.clock.now_ns()

    def _frames_header(self) -> FramesHeader:
        """The frames log's first line: the run, and the period and margin its frames are measured against."""
        config, profile = self.config, self.session.profile
        return FramesHeader(
            vsync_hz=profile.refresh_hz,
            period_ns=profile.period_ns,
            margin_ns=int(config.pacing.margin_ms * 1e6),
            virtual_time=config.run.virtual_time,
            method=self.session.spec,
            profile=profile.name,
            scene=self.session.scene.name,
            controller=config.controller.kind,
            seed=config.run.seed,
            config=config.source,
            hmdrt=__version__,
        )

    @staticmethod
    def _kernel_thread_count(config: RunConfig) -> int:
        wanted, most = config.run.kernel_threads, numba.config.NUMBA_NUM_THREADS
        if wanted > most:
            raise ConfigError(f"run.kernel_threads = {wanted}: numba has {most} threads (NUMBA_NUM_THREADS)")
        return wanted or most

    @contextmanager
    def _kernels(self) -> Iterator[None]:
        """The calling thread's numba kernels on run.kernel_threads threads (numba's setting is per thread)."""
        before = numba.get_num_threads()
        numba.set_num_threads(self._kernel_threads)
        try:
            yield
        finally:
            numba.set_num_threads(before)

    def _pacing(self, config: RunConfig) -> dict:
        """The pacer's settings from [pacing], checked against the display period."""
        p, period_ms = config.pacing, self.session.profile.period_ns / 1e6
        if p.margin_ms >= period_ms:
            raise ConfigError(f"pacing.margin_ms = {p.margin_ms} must be shorter than the period {period_ms:.2f} ms")
        offset = p.present_to_display_ms
        return {
            "margin_ns": int(p.margin_ms * 1e6),
            "present_to_display_ns": None if offset < 0 else int(offset * 1e6),
            "tail_quantile": p.tail_quantile or None,
            "tail_window": p.tail_window,
        }

    def _make_controller(self) -> BudgetController | None:
        """The hold-budget controller; without one, a controller that only widens the fovea while the gaze
        tracker is silent (when the fallback widens at all)."""
        c = self.config.controller
        if c.kind == "none":
            if not self.config.fallback.widen_deg_per_s:
                return None
            return BudgetController(self.session.method, ControllerConfig(adjust_level=False))
        settings = ControllerConfig(
            target_miss_rate=c.target_miss_rate,
            headroom=c.headroom,
            widen_latency_ms=c.widen_latency_ms,
            accuracy_deg=c.accuracy_deg,
        )
        return BudgetController(self.session.method, settings)

    # --- sampling -------------------------------------------------------------------------------------------------

    def _estimates(self, t_display: int, now: int) -> tuple[GazeEstimate | None, PoseEstimate | None, float]:
        """Gaze and pose for the display time, and the fallback's foveal widening in degrees: while the gaze
        device is silent, the fallback's gaze (the last good one, widened by the controller, then none: the
        screen centre)."""
        p = self.config.prediction
        gaze = self.store.gaze_at(t_display, now, p.gaze_device or None)
        pose = self.store.pose_at(t_display, now, p.pose_device or None)
        device = p.gaze_device or (gaze.device if gaze is not None else None)
        fallback = self.outages.judge(self.store.last_received(device) if device else None, now)
        return (None if fallback.centre else gaze), pose, fallback.widen_deg

    @staticmethod
    def _use(estimate) -> SampleUse | None:
        if estimate is None:
            return None
        held = estimate.blinking if isinstance(estimate, GazeEstimate) else estimate.tracking_lost
        return SampleUse(estimate.device, estimate.source_seq, estimate.source_t_host, estimate.predicted_ns, held)

    def _warp_target(self, t_vsync: int) -> tuple[dict[str, EyeCamera], SampleUse] | None:
        """The eye cameras at the head pose predicted for a repeated frame's display time."""
        pose = self.store.pose_at(t_vsync + self.pacer.present_to_display_ns, t_vsync, None)
        if pose is None:
            return None
        head = compose_pose(self.session.scene.start, pose)
        return eye_cameras(self.session.profile, head, self.session.eyes), self._use(pose)

    # --- one frame ------------------------------------------------------------------------------------------------

    def _render(self, timing: FrameTiming, woke: int, loop_ns: int = 0) -> Frame:
        """One frame's work from its wake-up: estimates, the controller's step, the method's render; its
        frame_ms adds loop_ns, the render loop's own work for it (planning, and handing over the frame before)."""
        t0 = time.perf_counter_ns()
        gaze, pose, widen_deg = self._estimates(timing.predicted_display_ns, woke)
        self._tune(None if gaze is None else gaze.speed_deg_s, widen_deg)
        stats = FrameStats()
        start = self.clock.now_ns()
        delay = int(self.config.pacing.render_delay_ms * 1e6)
        images, cameras, render_ns = self.session.render(
            timing.frame_id, gaze, pose, self.config.run.seed, stats, delay
        )
        end = self.clock.now_ns()
        frame = Frame(
            timing=timing,
            images=images,
            cameras=cameras,
            actual_wake_ns=woke,
            render_start_ns=start,
            render_end_ns=end,
            gaze=self._use(gaze),
            gaze_dirs=None if gaze is None else {"left": gaze.left, "right": gaze.right},
            head_pose=None if pose is None else (pose.position, pose.orientation),
            pose=self._use(pose),
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

    def _shown(self, record: FrameRecord, images: list[np.ndarray]) -> None:
        with self._lock:
            if record.shown != "repeat":
                if self._paced:
                    self.pacer.presented(record.frame_id, record.actual_present_ns)
                self._presents.append((record.frame_id, record.frame_ms, record.missed))
            self.report.add(record)
        self.shown_images = images
        frame = record.to_dict()
        self.telemetry.publish("frame", frame)
        if self.frames_log is not None:
            self.frames_log.offer(frame)
        if self.lsl is not None:
            self.lsl.offer(record, self.display.last)
        self.writer.offer(record.vsync, images)
        self.preview.offer(record, images, self.display.last.cameras, self.display.last.gaze_dirs)

    def _dropped(self, frame: Frame, t_vsync: int) -> None:
        with self._lock:
            if self._paced:
                self.pacer.presented(frame.timing.frame_id, t_vsync)
            self.report.drop(t_vsync)
        self._presents.append((frame.timing.frame_id, frame.frame_ms, True))

    def _tune(self, gaze_speed_deg_s: float | None, widen_deg: float) -> None:
        """Feed the controller the frames shown or dropped since the last call: their work on the wall clock
        (also in virtual time) against one period less the margin, the budget of the display's own rate; it
        widens the fovea for the gaze speed of the frame about to be rendered and the fallback's widen_deg."""
        while self._presents:  # only this thread takes from it: not empty stays not empty
            frame_id, frame_ms, missed = self._presents.popleft()
            if self.controller is None:
                continue
            self.controller.update(
                frame_id,
                int(frame_ms * 1e6),
                self.vsync.period_ns - self.pacer.margin_ns,
                missed,
                gaze_speed_deg_s,
                widen_deg,
            )

    def _apply_pending(self) -> None:
        with self._lock:
            pending, self._pending = self._pending, []
        for kind, value in pending:
            if kind == "method":
                self.session.set_method(value)
                self.controller = self._make_controller()
            elif kind == "reload":
                self._reload(value)

    # --- loops ----------------------------------------------------------------------------------------------------

    def _limits(self) -> tuple[int, float]:
        run = self.config.run
        return run.frames, run.duration_s

    def _done(self, frames: int, duration_s: float) -> bool:
        if self.stop.is_set():
            return True
        if frames and self.report.vsyncs >= frames:
            return True
        return bool(duration_s) and self.clock.now_ns() - self._started_ns >= duration_s * 1e9

    def _render_loop(self) -> None:
        frames, duration_s = self._limits()
        busy_since = time.perf_counter_ns()  # the loop's own work, outside its waits, counts to the next frame
        while not self._done(frames, duration_s):
            if self.display.backlog >= MAX_AHEAD:  # a stalled display: wait for it rather than run ahead of it
                self.stop.wait(self.vsync.period_ns / 1e9)
                busy_since = time.perf_counter_ns()
                continue
            self._apply_pending()
            with self._lock:
                timing = self.pacer.predict(self.clock.now_ns())
            loop_ns = time.perf_counter_ns() - busy_since
            if self.stop.wait(max(timing.wake_ns - self.clock.now_ns(), 0) / 1e9):
                break
            frame = self._render(timing, self.clock.now_ns(), loop_ns)
            busy_since = time.perf_counter_ns()
            self.display.submit(frame)
            with self._lock:
                self.pacer.mark_render(timing.frame_id, frame.actual_wake_ns, frame.render_end_ns)

    def _display_loop(self) -> None:
        frames, duration_s = self._limits()
        index = self.vsync.index_at_or_after(self.clock.now_ns())
        with self._kernels():
            while not self._done(frames, duration_s):
                if self.stop.wait(max(self.vsync.vsync(index) - self.clock.now_ns(), 0) / 1e9):
                    break
                self.display.latch(index)
                index += 1
        self.stop.set()

    def _virtual_loop(self) -> None:
        """One period per frame: the frame's work spans the period before the VSync it is shown at."""
        frames, duration_s = self._limits()
        period, index = self.vsync.period_ns, 0
        while not self._done(frames, duration_s):
            self._apply_pending()
            t_vsync = self.vsync.vsync(index)
            self.clock.advance_to(t_vsync - period)
            self.sources.poll()
            timing = FrameTiming(
                frame_id=index,
                wake_ns=t_vsync - period,
                desired_present_ns=t_vsync,
                predicted_display_ns=t_vsync + self.pacer.present_to_display_ns,
                period_ns=period,
                budget_ns=period,
                vsyncs=1,
            )
            frame = self._render(timing, self.clock.now_ns())
            self.display.submit(frame)
            self.clock.advance_to(t_vsync)
            self.display.latch(index)
            index += 1

    def run(self) -> dict:
        """Run until stopped, the frame count or the duration; returns the run report."""
        self.writer.start()
        if self.frames_log is not None:
            self.frames_log.start()
        if self.lsl is not None:
            self.lsl.start()
        stats = threading.Thread(target=self._stats_loop, name="stats", daemon=True)
        stats.start()
        switch = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)
        try:
            with self._kernels():
                if self.config.run.virtual_time:
                    self._virtual_loop()
                else:
                    display = threading.Thread(target=self._display_loop, name="display")
                    display.start()
                    try:
                        self._render_loop()
                    finally:
                        self.stop.set()
                        display.join()
        finally:
            sys.setswitchinterval(switch)
            self.stop.set()
            self.writer.close()
            if self.frames_log is not None:
                self.frames_log.close()
        return self.summary()  # the LSL outlets stay until close(): inlets may still be reading what they sent

    def _stats_loop(self) -> None:
        while not self.stop.wait(1.0):
            self.telemetry.publish("stats", self.summary())

    # --- control --------------------------------------------------------------------------------------------------

    def request_method(self, choice: MethodChoice) -> None:
        """Render with `choice` from the next frame on (applied between frames, with a new controller)."""
        with self._lock:
            self._pending.append(("method", choice))

    def reload(self) -> None:
        """Re-read the config file (SIGHUP); applied between frames, the bus stays up."""
        with self._lock:
            self._pending.append(("reload", self.config.source))

    def _reload(self, source: str) -> None:
        """Apply a re-read config's method, controller, prediction, fallback, pacing and output; a change of scene,
        display, drivers, bus or security needs a restart and is reported as such."""
        try:
            config, restart = reload_plan(self.config, load_config(source))
            if config.output.frames_log != self.config.output.frames_log:  # the open log stays as it runs
                restart.append("output.frames_log")
                output = msgspec.structs.replace(config.output, frames_log=self.config.output.frames_log)
                config = msgspec.structs.replace(config, output=output)
            pacing = self._pacing(config)
            check_folder(config.output.frames_dir)
            self.session.set_method(config.method_choice)
        except HmdrtError as exc:
            log.error("reload failed: %s", exc)
            return
        self.config = config
        self.writer.configure(config.output.frames_dir, config.output.every)
        with self._lock:
            self.pacer.configure(**pacing)
        self.store.horizon_ns = int(config.prediction.horizon_ms * 1e6)
        self.outages.config = config.fallback
        self.controller = self._make_controller()
        if restart:
            log.warning("reloaded %s; restart to change %s", source, ", ".join(restart))
        else:
            log.info("reloaded %s", source)

    def status(self) -> dict:
        with self._lock:
            pacing = self.pacer.info()
            shown = dict(self.report.shown)
        return {
            "method": self.session.spec,
            "params": self.session.params(),
            "profile": self.session.profile.name,
            "scene": self.session.scene.name,
            "vsync_hz": self.session.profile.refresh_hz,
            "shown": shown,
            "pacing": pacing,
            "devices": self.store.devices,
            "drivers": {device: msgspec.to_builtins(status) for device, status in list(self.ingest.status.items())},
            "endpoints": {
                "ingest": self.ingest.address,
                "telemetry": self.telemetry.address,
                "control": self.control.address,
            },
            "security": self.security(),
        }

    def security(self) -> dict:
        """Whether CURVE guards the bus and, if so, the handshakes it admitted and refused (clients without the
        keys are refused at the handshake, so their requests and samples never arrive); and the control commands
        and snapshot names refused."""
        refused = {"commands_refused": self.control.unauthorised, "snapshots_refused": self.snapshots_refused}
        if self.guard is None:
            return {"curve": False, **refused}
        return {"curve": True, **self.guard.counts(), **refused}

    def drivers(self) -> dict[str, dict]:
        out = {}
        for device, status in self.ingest.status.items():
            out[device] = {
                "samples": status.samples,
                "dropped": status.dropped,
                "invalid": status.invalid,
                "malformed": status.malformed,
                "reconnects": status.reconnects,
            }
        out.update(self.sources.counters())
        return out

    def display_info(self) -> dict:
        """What the frames are rendered for: the profile, per-eye pixels, the eyes and the refresh rate."""
        profile = self.session.profile
        return {
            "profile": profile.name,
            "width": profile.width,
            "height": profile.height,
            "eyes": list(self.session.eyes),
            "refresh_hz": profile.refresh_hz,
        }

    def image_buffers(self) -> dict[str, dict[str, int]]:
        """The rendered and warped images' pools: buffers held and allocated in all, steady after the first frames
        when no image is copied or leaked."""
        return {"rendered": counts(self.session.pools.values()), "warped": counts(self.display.warp_pools.values())}

    def summary(self) -> dict:
        """The run report so far. Only a copy of the counts is taken under the lock that the render and display
        threads share; the percentiles, over every frame so far, are worked out after it is released."""
        with self._lock:
            snapshot, pacing = self.report.snapshot(), self.pacer.info()
        report = snapshot.to_dict(
            method=self.session.method.name,
            method_spec=self.session.spec,
            profile=self.session.profile.name,
            display=self.display_info(),
            scene=self.session.scene.name,
            drivers=self.drivers(),
            samples={device: {**vars(c), "dropped": c.dropped} for device, c in self.store.counts().items()},
            pacing=pacing,
            virtual_time=self.config.run.virtual_time,
            seed=self.config.run.seed,
            ingest_malformed=self.ingest.malformed,
            outages=self.outages.to_dict(),
            devices_refused=self.store.devices_refused,
            **_not_written("frames_not_written", self.writer),
            **_not_written("frames_log_not_written", self.frames_log),
            **_not_written("lsl_not_pushed", self.lsl),
            config=self.config.source,
            hmdrt=__version__,
            security=self.security(),
            image_buffers=self.image_buffers(),
        )
        if self.controller is not None:
            report["controller"] = {
                "kind": self.config.controller.kind,
                "level": self.controller.level,
                "at_floor": self.controller.at_floor,
                "changes": self.controller.changes,
                "trajectory": list(self.controller.trajectory),
            }
        return report

    def close(self) -> None:
        self.stop.set()
        gc.unfreeze()  # a process that goes on (tests, a caller) collects them again
        if self.writer is not None:
            self.writer.close()
        if self.frames_log is not None:
            self.frames_log.close()
        if self.lsl is not None:
            self.lsl.close()
        if getattr(self, "_log", None) is not None:
            self._log.detach()  # before the telemetry socket closes
        # the preview before the telemetry it publishes on; the guard last: it answers the others
        for part in ("sources", "control", "ingest", "preview", "telemetry", "guard"):
            if getattr(self, part, None) is not None:
                getattr(self, part).close()
        self.session.close()


def _not_written(key: str, writer: BackgroundWriter | None) -> dict:
    """{key: what a background writer dropped (real time) or could not write}; {} where there is no such writer."""
    return {} if writer is None else {key: writer.skipped + writer.failed}
