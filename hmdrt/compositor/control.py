"""The control socket's commands, in one table: what each answers and whether it changes the compositor.

A request is a msgpack map {"cmd": name, ...} (hmdrt.compositor.endpoints.ControlServer decodes and size-caps
it); the reply is a map with "ok". A mutating command changes the compositor or writes a file, and with
CURVE security only an authenticated client may send one. Bad arguments get an error reply, never a
traceback; a method change is queued and applied between frames. A snapshot is written only into
[output] snapshot_dir, by plain file name and never over an existing file: a refused one is counted.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from hmdrt.errors import HmdrtError
from hmdrt.foveation import MethodChoice
from hmdrt.present.encode import side_by_side_srgb8, write_png

if TYPE_CHECKING:
    from hmdrt.compositor.daemon import Compositor

log = logging.getLogger(__name__)

# a file name and no more: no folder, no "..", not hidden, so a snapshot lands in snapshot_dir and nowhere else
SNAPSHOT_NAME = re.compile(r"(?!.*\.\.)[A-Za-z0-9_-][A-Za-z0-9._-]{0,200}\.png")


@dataclass(frozen=True)
class Command:
    run: Callable[[Compositor, dict], dict]
    mutating: bool  # changes the compositor or writes a file


def _status(comp: Compositor, request: dict) -> dict:
    return {"ok": True, **comp.status()}


def _stats(comp: Compositor, request: dict) -> dict:
    return {"ok": True, "report": comp.summary()}


def _set(comp: Compositor, request: dict) -> dict:
    """A new method ("method": "name?key=value") and/or new parameters ("params": {key: value}) over the method as
    it renders now; a bad name or value is answered now, not failed on later."""
    spec, params = request.get("method"), request.get("params", {})
    bad_params = not isinstance(params, dict) or not all(isinstance(k, str) for k in params)
    if not (isinstance(spec, str) or spec is None) or bad_params or (spec is None and not params):
        return {"ok": False, "error": 'set takes "method": "name?key=value" and/or "params": {key: value}'}
    choice = comp.session.current() if spec is None else MethodChoice.parse(spec)
    if params:
        choice = choice.with_options(**params)
    comp.request_method(choice)
    return {"ok": True, "method": str(choice)}


def _snapshot(comp: Compositor, request: dict) -> dict:
    """The frame shown last as a PNG in [output] snapshot_dir; the reply gives where. Any client of the control
    socket may ask, so the name may not lead elsewhere or replace a file."""
    name, images, folder = request.get("path"), comp.shown_images, Path(comp.config.output.snapshot_dir)
    if not isinstance(name, str) or not SNAPSHOT_NAME.fullmatch(name):
        return _refuse_snapshot(
            comp,
            f'snapshot takes "path": a file name such as "shown.png" (letters, digits, ".", "_", "-"; no folder '
            f"or ..), written to {folder}; got {repr(name)[:80]}",
        )
    if images is None:
        return {"ok": False, "error": "nothing has been shown yet"}
    path = folder / name
    try:
        write_png(path, side_by_side_srgb8(images), replace=False)
    except FileExistsError:
        return _refuse_snapshot(comp, f"snapshot: {path} exists; a snapshot never replaces a file")
    log.info("snapshot written to %s", path)
    return {"ok": True, "path": str(path)}


def _refuse_snapshot(comp: Compositor, error: str) -> dict:
    comp.snapshots_refused += 1
    log.warning("refused: %s", error)
    return {"ok": False, "error": error}


def _shutdown(comp: Compositor, request: dict) -> dict:
    comp.stop.set()
    return {"ok": True}


COMMANDS: dict[str, Command] = {
    "status": Command(_status, mutating=False),
    "stats": Command(_stats, mutating=False),
    "set": Command(_set, mutating=True),
    "snapshot": Command(_snapshot, mutating=True),
    "shutdown": Command(_shutdown, mutating=True),
}
MUTATING = frozenset(name for name, command in COMMANDS.items() if command.mutating)


def handle(comp: Compositor, request: dict) -> dict:
    """The reply to one decoded request."""
    command = COMMANDS.get(request["cmd"])
    if command is None:
        return {"ok": False, "error": f"unknown command {request['cmd']!r}; commands: {', '.join(COMMANDS)}"}
    try:
        return command.run(comp, request)
    except HmdrtError as exc:
        return {"ok": False, "error": str(exc)}
