"""docs/reference.md, made from what it describes: every subcommand's `--help` (the parser), the control commands
(their declarations in hmdrt.compositor.commands) and the run and eval configs (their msgspec schemas, each key's
type, limits and default), with the prose and the keys' meanings of hmdrt.cli.reference_text between them.

    python -m hmdrt.cli.reference > docs/reference.md

argparse wraps the help at COLUMNS, so it is made at WIDTH whatever the terminal. tests/test_cli_reference.py
makes it again and fails when docs/reference.md differs.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager

import msgspec
from msgspec import inspect as mi

from hmdrt.cli import build_parser
from hmdrt.cli import reference_text as text
from hmdrt.cli.schema import default, describe, description, fields
from hmdrt.compositor.commands import COMMANDS
from hmdrt.compositor.config import RunConfig
from hmdrt.evaluate.config import EvalConfig

WIDTH = 80  # COLUMNS while the help is formatted
COMMAND = "python -m hmdrt.cli.reference > docs/reference.md"


class Unexplained(Exception):
    """A config key without a meaning in hmdrt.cli.reference_text, or a meaning of a key that is no more."""


@contextmanager
def _columns(width: int) -> Iterator[None]:
    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = str(width)
    try:
        yield
    finally:
        if before is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = before


def parsers(parser: argparse.ArgumentParser, words: str = "") -> Iterator[tuple[str, argparse.ArgumentParser]]:
    """(words after `hmdrt`, parser) of the command and each subcommand that takes arguments of its own."""
    subparsers = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not words or not subparsers:
        yield words, parser
    for action in subparsers:
        for name, sub in action.choices.items():
            yield from parsers(sub, f"{words} {name}".strip())


def _command_line() -> list[str]:
    out = []
    with _columns(WIDTH):
        for words, parser in parsers(build_parser()):
            if words:
                out.append(f"### hmdrt {words}")
            out.append(f"```\n{parser.format_help().rstrip()}\n```")
            if words in text.AFTER_HELP:
                out.append(text.AFTER_HELP[words])
    return out


def _control_socket() -> list[str]:
    rows = ["| Command | Arguments | Changes the compositor | Does |", "|---|---|---|---|"]
    for name, command in COMMANDS.items():
        arguments = "; ".join(
            f"`{f.name}`: {description(f.type)}; {describe(f.type)}{'' if f.required else ', optional'}"
            for f in fields(command)
        )
        does = " ".join((command.__doc__ or "").split())
        rows.append(f"| `{name}` | {arguments or '-'} | {'yes' if command.mutating else 'no'} | {does} |")
    return ["## Control socket", text.CONTROL_BEFORE, "\n".join(rows), text.CONTROL_AFTER]


def _struct_of(t: mi.Type) -> tuple[type | None, bool]:
    """The struct a field holds (a section, or with True an array of them), or None."""
    while isinstance(t, mi.Metadata):
        t = t.type
    if isinstance(t, mi.UnionType):
        structs = [u for u in t.types if isinstance(u, mi.StructType)]
        t = structs[0] if structs else t
    if isinstance(t, mi.ListType) and isinstance(t.item_type, mi.StructType):
        return t.item_type.cls, True
    return (t.cls, False) if isinstance(t, mi.StructType) else (None, False)


def _table(keys: list[tuple[str, mi.Field]], meanings: dict[str, str], used: set[str]) -> str:
    rows = ["| Key | Type | Default | Meaning |", "|---|---|---|---|"]
    for key, field in keys:
        meaning = description(field.type) or meanings.get(key)
        if not meaning:
            raise Unexplained(f"config key {key} has no meaning: add one to hmdrt/cli/reference_text.py")
        used.add(key)
        value = default(field)
        rows.append(
            f"| `{field.name}` | {describe(field.type)} | {value if value == 'required' else f'`{value}`'} "
            f"| {meaning} |"
        )
    return "\n".join(rows)


def _config(root: type[msgspec.Struct], meanings: dict[str, str], sections: dict[str, tuple[str, str]]) -> list[str]:
    """A config's sections, each a table of its keys between its prose."""
    used: set[str] = set()
    top, nested = [], []
    for field in fields(root):
        if field.name not in text.NOT_IN_FILES:
            (nested if _struct_of(field.type)[0] else top).append(field)
    out = []
    parts = [("", "Top level", [(f.name, f) for f in top], "")]
    for field in nested:
        struct, array = _struct_of(field.type)
        value = default(field)
        note = f"Default: `{field.name} = {value}`." if array and value not in ("[]", "required") else ""
        heading = f"[[{field.name}]]" if array else f"[{field.name}]"
        parts.append((field.name, heading, [(f"{field.name}.{f.name}", f) for f in fields(struct)], note))
    for name, heading, keys, note in parts:
        before, after = sections.get(name, ("", ""))
        out += [f"### {heading}", before, note, _table(keys, meanings, used), after]
    if stale := sorted(set(meanings) - used):
        raise Unexplained(f"hmdrt/cli/reference_text.py explains config keys that are no more: {', '.join(stale)}")
    return out


def reference() -> str:
    """docs/reference.md as it should read."""
    blocks = [
        text.HEADER,
        *_command_line(),
        *_control_socket(),
        text.RUN_CONFIG,
        *_config(RunConfig, text.RUN_MEANINGS, text.RUN_SECTIONS),
        text.RELOAD,
        text.EVAL_CONFIG,
        *_config(EvalConfig, text.EVAL_MEANINGS, text.EVAL_SECTIONS),
    ]
    return "\n\n".join(block for block in blocks if block) + "\n"


def main() -> int:
    try:
        sys.stdout.write(reference())
    except Unexplained as exc:
        print(f"hmdrt.cli.reference: {exc}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
