"""The control socket's commands, declared once: each one's name, arguments with their types and limits, whether it
changes the compositor, and what it does.

The control socket (hmdrt.compositor.control), the live page (hmdrt.watch.protocol) and `hmdrt ctl` check a request
with parse() here, so a bad one is refused with the same one line wherever it was sent; docs/reference.md's table
of commands is made from these declarations. What only the running compositor can tell (whether a method or a
parameter value exists) it checks itself, and its answer travels back unchanged.

A command is a msgspec struct tagged by its "cmd"; `mutating` says whether it changes the compositor or writes a
file (with CURVE security only an authenticated client may send one), `takes` its arguments in words.
"""

from __future__ import annotations

import json
import re
from typing import Annotated, ClassVar

import msgspec

from hmdrt.errors import HmdrtError

MAX_TEXT = 200  # characters of a method spec or a parameter's string value
MAX_PARAMS = 32
MAX_NAME = 64  # characters of a parameter's name

# a file name and no more: no folder, no "..", not hidden, so a snapshot lands in snapshot_dir and nowhere else
SNAPSHOT_NAME = re.compile(r"(?!.*\.\.)[A-Za-z0-9_-][A-Za-z0-9._-]{0,123}\.png")

Spec = Annotated[
    str, msgspec.Meta(min_length=1, max_length=MAX_TEXT, description='a method with options, "name?key=value"')
]
Params = Annotated[
    dict[
        Annotated[str, msgspec.Meta(min_length=1, max_length=MAX_NAME)],
        Annotated[str, msgspec.Meta(max_length=MAX_TEXT)] | int | float | bool,
    ],
    msgspec.Meta(max_length=MAX_PARAMS, description="parameters of the method as it renders, {key: value}"),
]
FileName = Annotated[
    str, msgspec.Meta(min_length=5, max_length=128, description='a file name in [output] snapshot_dir, "shown.png"')
]

NOT_A_COMMAND = 'a command is a map with a "cmd" string'


class BadCommand(HmdrtError):
    """A request that is not a command as declared here; its text says why, in one line."""


class Command(msgspec.Struct, frozen=True, forbid_unknown_fields=True, omit_defaults=True, tag_field="cmd"):
    """A control command; its docstring's first line says what it does, for the reference."""

    mutating: ClassVar[bool] = False  # changes the compositor or writes a file
    takes: ClassVar[str] = ""  # its arguments in words ("": none)

    @classmethod
    def name(cls) -> str:
        return cls.__struct_config__.tag


class Status(Command, tag="status"):
    """Method, parameters, profile, scene, VSync rate, frames shown, pacing, devices, drivers (each one's newest
    status on the bus: state, counts, clock estimate), endpoints, security."""


class Stats(Command, tag="stats"):
    """The run report so far, as "report"."""


class Set(Command, tag="set"):
    """Changes the method or its parameters between frames; the reply's "method" is the one that will render."""

    mutating = True
    takes = '"method": "name?key=value" and/or "params": {key: value}'
    method: Spec | None = None
    params: Params | None = None

    def __post_init__(self) -> None:
        if self.method is None and not self.params:
            raise ValueError("got neither")


class Snapshot(Command, tag="snapshot"):
    """Writes the frame shown last, eyes side by side, as a PNG into [output] snapshot_dir (never over a file; a
    refusal is counted); the reply's "path" is where. Without a name, one of the time: snapshot-DATE-TIME-MS.png."""

    mutating = True
    takes = '"path": a file name such as "shown.png" (letters, digits, ".", "_", "-"; no folder or ".."), or none'
    path: FileName | None = None

    def __post_init__(self) -> None:
        if self.path is not None and not SNAPSHOT_NAME.fullmatch(self.path):
            raise ValueError(f"got {self.path[:80]!r}")


class Shutdown(Command, tag="shutdown"):
    """Stops the compositor; its run report is written."""

    mutating = True


COMMANDS: dict[str, type[Command]] = {c.name(): c for c in (Status, Stats, Set, Snapshot, Shutdown)}
MUTATING = frozenset(name for name, command in COMMANDS.items() if command.mutating)


def parse(request: object) -> Command:
    """The command of a decoded request ({"cmd": name, argument: value, ...}); BadCommand saying what is wrong."""
    if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
        raise BadCommand(NOT_A_COMMAND)
    name = request["cmd"]
    command = COMMANDS.get(name)
    if command is None:
        raise BadCommand(f"unknown command {name[:64]!r}; commands: {', '.join(COMMANDS)}")
    try:
        return msgspec.convert(request, command)
    except msgspec.ValidationError as exc:
        raise BadCommand(f"{name} takes {command.takes or 'no arguments'}; {_problem(str(exc))}") from None


def to_request(command: Command) -> dict:
    """The request of a command, as the control socket takes it: "cmd" and the arguments given."""
    return msgspec.to_builtins(command)


def _problem(text: str) -> str:
    """msgspec's account of a value that does not fit, in the words of a command's arguments."""
    what, _, where = text.partition(" - at ")
    what = what.replace(" | null", "").replace("Object", "object")
    if unknown := re.fullmatch(r"object contains unknown field `(.*)`", what):
        return f"unknown argument {unknown[1][:64]!r}"
    where = re.sub(r"`\$\.(\w+)\[\.\.\.\]`", r"a value of \1", where.replace("`key` in ", "a key of "))
    where = where.replace("`$.", "").replace("`", "")
    what = what[:1].lower() + what[1:]
    return f"{where}: {what}" if where else what


def from_words(name: str, words: list[str]) -> Command:
    """The command of `hmdrt ctl NAME ARG=VALUE ...`, each VALUE typed once, by its argument: a string argument
    takes it as it is, another reads it as JSON; ARG.KEY=VALUE sets one entry of a table argument (VALUE JSON, or
    else a string). Checked as the control socket checks it (BadCommand)."""
    request: dict = {"cmd": name}
    command = COMMANDS.get(name)
    if command is None:
        return parse(request)  # unknown: parse() says so
    fields = {f.name: f.type for f in msgspec.inspect.type_info(command).fields}
    for word in words:
        key, equals, value = word.partition("=")
        arg, dot, entry = key.partition(".")
        if not equals or not arg:
            raise BadCommand(f"{word[:80]!r} is not ARG=VALUE")
        kind = fields.get(arg)
        if dot:
            table = request.setdefault(arg, {})
            if not isinstance(table, dict) or not (kind is None or _is(kind, msgspec.inspect.DictType)):
                raise BadCommand(f"{name} takes {command.takes or 'no arguments'}; {arg} is not a table")
            table[entry] = _json(value, otherwise=value)
        else:
            typed = kind is None or _is(kind, msgspec.inspect.StrType)  # not an argument: parse() names it
            request[arg] = value if typed else _json(value, otherwise=_NOT_JSON)
            if request[arg] is _NOT_JSON:
                raise BadCommand(f"{arg}={value[:80]}: not JSON (a table is {{...}}, a string in double quotes)")
    return parse(request)


_NOT_JSON = object()


def _json(text: str, otherwise: object) -> object:
    try:
        return json.loads(text)
    except ValueError:
        return otherwise


def _is(kind: msgspec.inspect.Type | None, wanted: type) -> bool:
    """Whether an argument's type is (or may be) `wanted`, through its metadata and unions."""
    if isinstance(kind, msgspec.inspect.Metadata):
        return _is(kind.type, wanted)
    if isinstance(kind, msgspec.inspect.UnionType):
        return any(_is(t, wanted) for t in kind.types)
    return isinstance(kind, wanted)
