"""The control socket's commands, in one table: what each answers and whether it changes the compositor.

A request is a msgpack map {"cmd": name, ...} (hmdrt.compositor.endpoints.ControlServer decodes and size-caps
it); the reply is a map with "ok". A mutating command changes the compositor or writes a file, and with
CURVE security only an authenticated client may send one. Bad arguments get an error reply, never a
traceback; a method change is queued and applied between frames.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from hmdrt.errors import HmdrtError
from hmdrt.foveation import MethodChoice
from hmdrt.present.encode import side_by_side_srgb8, write_png

if TYPE_CHECKING:
    from hmdrt.compositor.daemon import Compositor


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
    path, images = request.get("path"), comp.shown_images
    if not isinstance(path, str) or not path.endswith(".png"):
        return {"ok": False, "error": 'snapshot takes "path": "out.png"'}
    if images is None:
        return {"ok": False, "error": "nothing has been shown yet"}
    write_png(Path(path), side_by_side_srgb8(images))
    return {"ok": True, "path": path}


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
