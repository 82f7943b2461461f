"""The hmdrt command line (docs/reference.md, Command line): one module per group of subcommands, each adding its
parsers with add_commands(). Strings become checked values in the parser (hmdrt.cli.common's argument types), and
errors reach the user as one line, never a traceback."""

from __future__ import annotations

import argparse
import re
import sys

from hmdrt.cli import compositor, devices, render, results
from hmdrt.cli.common import Parser
from hmdrt.console import logs
from hmdrt.errors import HmdrtError
from hmdrt.version import __version__

GROUPS = (render, devices, compositor, results)  # in the order `hmdrt --help` lists their subcommands


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="hmdrt", description="A simulated HMD runtime with foveated ray tracing.")
    parser.add_argument("--version", action="version", version=f"hmdrt {__version__}")
    parser.add_argument(
        "--log-level", choices=logs.LEVELS, default="warning", help="log records shown on stderr (default warning)"
    )
    parser.add_argument(
        "-v", "--verbose", dest="log_level", action="store_const", const="info", help="the same as --log-level info"
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for group in GROUPS:
        group.add_commands(sub)
    return parser


NEGATIVE = re.compile(r"-\d[\d.]*(,-?\d[\d.]*)*")  # "-10,5", "-2.5": a value, though argparse takes it for a flag


def _negative_values(argv: list[str]) -> list[str]:
    """`--option -10,5` as `--option=-10,5`, so that a negative gaze or number after an option reads as its value."""
    out: list[str] = []
    for arg in argv:
        if out and out[-1].startswith("--") and "=" not in out[-1] and NEGATIVE.fullmatch(arg):
            out[-1] = f"{out[-1]}={arg}"
        else:
            out.append(arg)
    return out


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(_negative_values(sys.argv[1:] if argv is None else argv))
    logs.configure(args.log_level)
    try:
        return args.run(args)
    except HmdrtError as exc:
        print(f"hmdrt: error: {exc}", file=sys.stderr)
        return 1
    except MemoryError:
        print("hmdrt: error: out of memory; try a smaller --resolution or scene", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130
