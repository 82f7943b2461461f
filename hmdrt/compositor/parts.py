"""The compositor as its loops (hmdrt.compositor.loops) and its status and report (hmdrt.compositor.status) see it:
the parts they read and drive, named here so that neither imports the daemon that owns them."""

from __future__ import annotations

import threading
from typing import Protocol

from hmdrt.bus.security import Guard
from hmdrt.clock import Clock
from hmdrt.compositor.clock import VsyncClock
from hmdrt.compositor.config import RunConfig
from hmdrt.compositor.display import Display
from hmdrt.compositor.endpoints import ControlServer, Ingest, Telemetry
from hmdrt.compositor.fallback import Outages
from hmdrt.compositor.frames import FrameBuilder
from hmdrt.compositor.pacer import Pacer
from hmdrt.compositor.samples import SampleStore
from hmdrt.compositor.session import Session
from hmdrt.compositor.sinks import Sink
from hmdrt.compositor.sources import Sources
from hmdrt.telemetry.report import RunReport


class Parts(Protocol):
    """What hmdrt.compositor.daemon.Compositor holds, as far as the loops, the status and the report use it."""

    config: RunConfig
    clock: Clock
    session: Session
    store: SampleStore
    report: RunReport
    vsync: VsyncClock
    pacer: Pacer
    lock: threading.Lock  # the pacer's and the report's: the render and display threads share them
    stop: threading.Event
    display: Display
    builder: FrameBuilder
    outages: Outages
    sinks: list[Sink]
    ingest: Ingest
    sources: Sources
    telemetry: Telemetry
    control: ControlServer
    guard: Guard | None
    snapshots_refused: int
    kernel_threads: int
    started_ns: int

    def apply_pending(self) -> None:
        """Apply the changes asked for since the last frame (between frames, on the render thread)."""

    def summary(self) -> dict:
        """The run report so far."""
