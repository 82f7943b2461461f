"""What the control socket's commands do; hmdrt.compositor.commands declares them (arguments, limits, which mutate).

A request is a msgpack map {"cmd": name, ...} (hmdrt.compositor.endpoints.ControlServer decodes and size-caps
it, and refuses a mutating command to a client that may not send one); the reply is a map with "ok". A request
that is not a declared command gets commands.parse's one line, never a traceback; a method change is queued
and applied between frames. A snapshot is written only into [output] snapshot_dir, by plain file name and never
over an existing file: a refused one is counted.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from hmdrt.compositor import commands
from hmdrt.compositor.commands import BadCommand, Command, Set, Shutdown, Snapshot, Stats, Status
from hmdrt.compositor.config import RunConfig
from hmdrt.compositor.session import Session
from hmdrt.errors import HmdrtError
from hmdrt.foveation import MethodChoice
from hmdrt.present.encode import side_by_side_srgb8, write_png

log = logging.getLogger(__name__)

MUTATING = commands.MUTATING  # what the control socket refuses to a client that may only read


class Compositor(Protocol):
    """What the commands read and change of a running compositor (hmdrt.compositor.daemon.Compositor)."""

    config: RunConfig
    session: Session
    shown_images: list | None
    snapshots_refused: int
    stop: threading.Event

    def status(self) -> dict: ...

    def summary(self) -> dict: ...

    def request_method(self, choice: MethodChoice) -> None: ...


def _status(comp: Compositor, command: Status) -> dict:
    return {"ok": True, **comp.status()}


def _stats(comp: Compositor, command: Stats) -> dict:
    return {"ok": True, "report": comp.summary()}


def _set(comp: Compositor, command: Set) -> dict:
    """A new method and/or new parameters over the method as it renders now; a bad name or value is answered now,
    not failed on later."""
    choice = comp.session.current() if command.method is None else MethodChoice.parse(command.method)
    if command.params:
        choice = choice.with_options(**command.params)
    comp.request_method(choice)
    return {"ok": True, "method": str(choice)}


def _snapshot(comp: Compositor, command: Snapshot) -> dict:
    """The frame shown last as a PNG in [output] snapshot_dir, by the name given or one of the time; the reply
    gives where. Any client of the control socket may ask, so a name that exists is refused, not replaced."""
    images = comp.shown_images
    if images is None:
        return {"ok": False, "error": "nothing has been shown yet"}
    path = Path(comp.config.output.snapshot_dir) / (command.path or time_name())
    try:
        write_png(path, side_by_side_srgb8(images), replace=False)
    except FileExistsError:
        return _refuse_snapshot(comp, f"snapshot: {path} exists; a snapshot never replaces a file")
    log.info("snapshot written to %s", path)
    return {"ok": True, "path": str(path)}


def time_name(now: float | None = None) -> str:
    """A snapshot's name when none is given: snapshot-DATE-TIME-MS.png, local time."""
    now = time.time() if now is None else now
    return f"snapshot-{time.strftime('%Y%m%d-%H%M%S', time.localtime(now))}-{int(now * 1e3) % 1000:03d}.png"


def _refuse_snapshot(comp: Compositor, error: str) -> dict:
    comp.snapshots_refused += 1
    log.warning("refused: %s", error)
    return {"ok": False, "error": error}


def _shutdown(comp: Compositor, command: Shutdown) -> dict:
    comp.stop.set()
    return {"ok": True}


RUN: dict[type[Command], Callable[[Compositor, Any], dict]] = {
    Status: _status,
    Stats: _stats,
    Set: _set,
    Snapshot: _snapshot,
    Shutdown: _shutdown,
}


def handle(comp: Compositor, request: dict) -> dict:
    """The reply to one decoded request."""
    try:
        command = commands.parse(request)
    except BadCommand as exc:
        if request.get("cmd") == "snapshot":
            return _refuse_snapshot(comp, str(exc))
        return {"ok": False, "error": str(exc)}
    try:
        return RUN[type(command)](comp, command)
    except HmdrtError as exc:
        return {"ok": False, "error": str(exc)}
