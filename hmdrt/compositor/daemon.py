"""`hmdrt run CONFIG.toml`: the compositor daemon, which wires its parts together and owns them.

Each frame, as a compositor pacer schedules it (Monado's u_pacing; hmdrt.compositor.pacer): wake at the predicted
time, sample gaze and head pose predicted for the frame's display time from what has arrived, render through the
method (hmdrt.compositor.frames), and hand the frame to the display, which latches it at its VSync or, when it is
late, shows the last frame again timewarped to the newest head pose. Each VSync's frame goes to the sinks
(hmdrt.compositor.sinks): the gaze error at photon time (hmdrt.compositor.gaze_error), the `frame` telemetry, the
frames log, the LSL outlets, the frames on disk (hmdrt.present.output) and previews (`preview`,
hmdrt.compositor.preview) while a client subscribes to them. The loops, in real and in virtual time, are
hmdrt.compositor.loops's; the status and the run report, which goes out each second (`stats`) and is written at the
end, also after SIGTERM, hmdrt.compositor.status's; the control socket's commands hmdrt.compositor.control's; and
what a reload may change hmdrt.compositor.config.reload_plan's.
"""

from __future__ import annotations

import gc
import logging
import threading
from functools import partial

import msgspec
import numpy as np
import zmq

from hmdrt.bus.local import bind_endpoints
from hmdrt.bus.security import Guard, ServerKeys, check_binds
from hmdrt.clock import MONOTONIC, Clock, VirtualClock
from hmdrt.compositor import control, loops, status
from hmdrt.compositor.clock import VsyncClock
from hmdrt.compositor.config import RunConfig, load_config, reload_plan
from hmdrt.compositor.control import MUTATING
from hmdrt.compositor.controller import make_controller
from hmdrt.compositor.display import Display, Frame
from hmdrt.compositor.endpoints import ControlServer, Ingest, Telemetry
from hmdrt.compositor.fallback import Outages
from hmdrt.compositor.frames import FrameBuilder
from hmdrt.compositor.gaze_error import GazeErrors
from hmdrt.compositor.lsl_outlets import LslOutlets
from hmdrt.compositor.pacer import Pacer, pacing_settings
from hmdrt.compositor.preview import PREVIEW, PreviewPublisher
from hmdrt.compositor.samples import SampleStore
from hmdrt.compositor.session import Session
from hmdrt.compositor.sinks import FrameTelemetry, LoggedFrames, Shown, Sink, WrittenFrames
from hmdrt.compositor.sources import Sources
from hmdrt.compositor.startup import Startup
from hmdrt.console.logs import TelemetryHandler
from hmdrt.errors import HmdrtError
from hmdrt.foveation import MethodChoice
from hmdrt.present.output import FrameWriter, check_folder
from hmdrt.telemetry.frames_log import FramesLog
from hmdrt.telemetry.report import FrameRecord, RunReport

log = logging.getLogger(__name__)

FIRST_PRESENT_NS = 50_000_000  # Monado's fake pacer: the first present is assumed 50 ms out
CONNECT_WAIT_S = 3.0  # how long the start waits for its drivers to connect (a device may come later)


class Compositor:
    """The daemon: its parts, wired together at start, the sinks its shown frames go to, and the changes asked for
    between frames. hmdrt.compositor.loops drives the parts and hmdrt.compositor.status reads them."""

    def __init__(
        self,
        config: RunConfig,
        clock: Clock | None = None,
        context: zmq.Context | None = None,
        startup: Startup | None = None,
    ):
        self.config = config
        self.startup = startup or Startup()
        virtual = config.run.virtual_time
        self.clock = clock or (VirtualClock(0) if virtual else MONOTONIC)
        self._paced = not virtual  # virtual time schedules each frame over the period before its VSync
        # loopback only, or CURVE with [security]: checked, and the keys read, before any start-up work; by default
        # each socket is ipc:// in a folder of this user's only
        security = config.security
        configured = msgspec.structs.asdict(config.bus)
        check_binds({f"bus.{k}": v for k, v in configured.items()}, security is not None)
        server_keys = ServerKeys.load(security.server_key, security.allowed_clients) if security else None
        endpoints = bind_endpoints(configured)
        self.kernel_threads = loops.kernel_threads(config)
        # on a first run this compiles half of what the tracer calls, while a second process compiles the other half
        self.startup.step("setting up the scene and the tracer")
        self.session = Session(config)
        self.store = SampleStore()
        self.report = RunReport(self.session.profile.refresh_hz, config.run.warmup_s)
        self.outages = Outages()
        self.lock = threading.Lock()  # pacer and report: the render and display threads share them
        self._pending: list[tuple[str, object]] = []  # control changes applied between frames
        # where each shown frame goes, in order: the gaze error, the `frame` telemetry, frames log, LSL outlets, frames
        # on disk, preview
        self.sinks: list[Sink] = []
        self.lsl: LslOutlets | None = None
        self.shown_images: list[np.ndarray] | None = None
        self.snapshots_refused = 0  # snapshot names that led out of the snapshot folder or to an existing file
        self.stop = threading.Event()
        self._context = context or zmq.Context.instance()
        try:
            if config.output.frames_log:  # opened before the start-up's work: a path it cannot write fails at once
                header = status.frames_header(config, self.session)
                self.sinks.append(LoggedFrames(FramesLog(config.output.frames_log, header, block=virtual)))
            if config.lsl.outlets:  # likewise: without pylsl it fails at once
                self.lsl = LslOutlets(config.lsl.outlets, self.clock, block=virtual)
                self.sinks.append(self.lsl)
            self.guard = Guard(self._context, server_keys) if server_keys else None  # before any bind
            self.telemetry = Telemetry(self._context, endpoints["telemetry"], self.guard, on_demand=(PREVIEW,))
            self.sinks.insert(0, FrameTelemetry(self.telemetry))
            # first of all: it puts into each record the gaze errors that the others carry
            eyes, device = self.session.eyes, lambda: self.config.prediction.gaze_device
            self.sinks.insert(0, GazeErrors(self.store, self.clock, eyes, device))
            self.preview = PreviewPublisher(self.telemetry)
            self.sinks.append(self.preview)
            self._log = TelemetryHandler(self.telemetry.publish)
            self._log.attach()
            self.ingest = Ingest(self._context, endpoints["ingest"], self.store.add, self.clock, self.guard)
            self.sources = Sources(
                [d.url for d in config.drivers],
                self.clock,
                virtual,
                self.ingest.address,
                self.store.add,
                keys=self.guard.own_keys if self.guard else None,
            )
            # compiled kernels, allocated buffers and connected drivers before the VSync clock starts
            self.startup.step(f"compiling {self.session.choice.name}'s kernels and the timewarp")
            self.session.warm_up()
            self.startup.step("connecting drivers")
            self.sources.wait_connected(CONNECT_WAIT_S)
            self.startup.end()
            # and no collection of what start-up built: a full one scanned its ~180k objects, stopping every
            # thread for ~120 ms (four frames at 30 Hz) whenever it came; frozen, it takes microseconds
            gc.collect()
            gc.freeze()
            self.vsync = VsyncClock(self.session.profile.period_ns, self.clock.now_ns() + FIRST_PRESENT_NS)
            self.pacer = Pacer(self.vsync)
            self.builder = FrameBuilder(config, self.session, self.store, self.outages, self.clock, self.pacer)
            out = config.output  # the video's rate is fixed at start: a reload keeps output.video and output.every
            self.writer = FrameWriter(out.video, self.session.profile.refresh_hz / out.every, block=virtual)
            self.sinks.insert(self.sinks.index(self.preview), WrittenFrames(self.writer))  # the preview last
            self.display = Display(
                self.vsync,
                self.clock,
                self.builder.warp_target,
                self._shown,
                self._dropped,
                warp_deadline=not virtual,
                warp_pools=self.session.warp_pools,
            )
            self.apply(config)
            self.control = ControlServer(
                self._context, endpoints["control"], partial(control.handle, self), MUTATING, self.guard
            )
            status.warn_if_open(self)
        except (HmdrtError, ValueError):
            self.close()
            raise
        self.started_ns = self.clock.now_ns()

    def apply(self, config: RunConfig) -> None:
        """Adopt `config`'s method, controller, prediction, fallback, pacing and output folder and rate: at start, and
        on a reload once reload_plan has kept what needs a restart. HmdrtError, with none of them changed, when the
        pacing, the frames folder or the method cannot be used."""
        pacing = pacing_settings(config.pacing, self.vsync.period_ns)
        check_folder(config.output.frames_dir)
        self.session.set_method(config.method_choice)
        self.config = self.builder.config = config
        self.writer.configure(config.output.frames_dir, config.output.every)
        with self.lock:
            self.pacer.configure(**pacing)
        self.store.horizon_ns = int(config.prediction.horizon_ms * 1e6)
        self.store.expiry_ns = self.ingest.expiry_ns = int(config.fallback.centre_after_ms * 1e6)  # devices' slots
        self.store.saccades = config.gaze.saccade_prediction
        self.outages.config = config.fallback
        self.builder.controller = make_controller(config, self.session.method)

    # --- the display's callbacks (display thread) -----------------------------------------------------------------

    def _shown(self, record: FrameRecord, images: list[np.ndarray]) -> None:
        """After each VSync that showed something: the pacer, the controller and the report learn of it, then each
        sink is offered it."""
        with self.lock:
            if record.shown != "repeat":
                if self._paced:
                    self.pacer.presented(record.frame_id, record.actual_present_ns)
                self.builder.presents.append((record.frame_id, record.frame_ms, record.missed, record.rays))
            self.report.add(record)
        self.shown_images = images
        shown = Shown(record, images, self.display.last)
        for sink in self.sinks:
            sink.offer(shown)

    def _dropped(self, frame: Frame, t_vsync: int) -> None:
        with self.lock:
            if self._paced:
                self.pacer.presented(frame.timing.frame_id, t_vsync)
            self.report.drop(t_vsync)
        self.builder.presents.append((frame.timing.frame_id, frame.frame_ms, True, frame.rays))

    # --- running --------------------------------------------------------------------------------------------------

    def run(self) -> dict:
        """Run until stopped, the frame count or the duration; returns the run report."""
        for sink in self.sinks:
            sink.start()
        try:
            loops.run(self)
        finally:
            for sink in self.sinks:
                sink.finish()
        return self.summary()

    def apply_pending(self) -> None:
        """The method changes and reloads asked for since the last frame (render thread, between frames)."""
        with self.lock:
            pending, self._pending = self._pending, []
        for kind, value in pending:
            if kind == "method":
                self.session.set_method(value)
                self.builder.controller = make_controller(self.config, self.session.method)
            elif kind == "reload":
                self._reload(value)

    # --- control --------------------------------------------------------------------------------------------------

    def request_method(self, choice: MethodChoice) -> None:
        """Render with `choice` from the next frame on (applied between frames, with a new controller)."""
        with self.lock:
            self._pending.append(("method", choice))

    def reload(self) -> None:
        """Re-read the config file (SIGHUP); applied between frames, the bus stays up."""
        with self.lock:
            self._pending.append(("reload", self.config.source))

    def _reload(self, source: str) -> None:
        """Apply a re-read config's method, controller, prediction, fallback, pacing and output; a change of scene,
        display, drivers, bus, security or the frames log needs a restart and is reported as such."""
        try:
            config, restart = reload_plan(self.config, load_config(source))
            if config.output.frames_log != self.config.output.frames_log:  # the open log stays as it runs
                restart.append("output.frames_log")
                output = msgspec.structs.replace(config.output, frames_log=self.config.output.frames_log)
                config = msgspec.structs.replace(config, output=output)
            self.apply(config)
        except HmdrtError as exc:
            log.error("reload failed: %s", exc)
            return
        if restart:
            log.warning("reloaded %s; restart to change %s", source, ", ".join(restart))
        else:
            log.info("reloaded %s", source)

    def status(self) -> dict:
        return status.status(self)

    def security(self) -> dict:
        return status.security(self)

    def summary(self) -> dict:
        """The run report so far."""
        return status.summary(self)

    def close(self) -> None:
        self.stop.set()
        gc.unfreeze()  # a process that goes on (tests, a caller) collects them again
        for sink in self.sinks:  # the preview among them, before the telemetry it publishes on
            sink.close()
        if getattr(self, "_log", None) is not None:
            self._log.detach()  # before the telemetry socket closes
        for part in ("sources", "control", "ingest", "telemetry", "guard"):  # the guard last: it answers the others
            if getattr(self, part, None) is not None:
                getattr(self, part).close()
        self.session.close()
