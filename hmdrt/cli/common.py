"""What the subcommands share: usage errors in one line, argument types that turn a string into a checked value
once (at the edge, so a command's code gets typed values), the options of a client of a running compositor,
and the signals that stop a long-running command."""

from __future__ import annotations

import argparse
import json
import math
import signal
import threading
from pathlib import Path

from hmdrt.bus.local import KINDS, check_endpoint, find_endpoint
from hmdrt.bus.security import ClientKeys
from hmdrt.files.atomic import write_atomic

UNTIL = "stop after SEC seconds (default: until SIGINT/SIGTERM)"


class Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line."""

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def count(text: str) -> int:
    """A whole number of at least 1 (frames, threads)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def seconds(text: str) -> float:
    """A positive, finite number of seconds (--duration, --timeout)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (value > 0 and math.isfinite(value)):
        raise argparse.ArgumentTypeError(f"must be positive, got {text}")
    return value


def write_json(path: str | Path, record: dict) -> None:
    write_atomic(path, (json.dumps(record, indent=2) + "\n").encode())


def stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM, so long-running commands stop cleanly."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def key_options(parser: argparse.ArgumentParser) -> None:
    """--server-key and --client-key: connect as a CURVE client to a compositor with [security]."""
    parser.add_argument(
        "--server-key", metavar="PUBLIC_KEY_FILE", help="the compositor's public key (NAME.key): connect with CURVE"
    )
    parser.add_argument(
        "--client-key", metavar="SECRET_KEY_FILE", help="this client's secret key (NAME.key_secret), on its allow-list"
    )


def client_keys(args: argparse.Namespace) -> ClientKeys | None:
    return ClientKeys.from_options(args.server_key, args.client_key)


def control_options(parser: argparse.ArgumentParser) -> None:
    """--control, --timeout and the CURVE keys: how a client reaches a running compositor's control socket."""
    parser.add_argument(
        "--control",
        help="its control endpoint (default: this user's one running compositor, ipc:// in $XDG_RUNTIME_DIR/hmdrt)",
    )
    parser.add_argument("--timeout", type=seconds, default=2.0, help="seconds to wait for an answer (default 2)")
    key_options(parser)


def endpoint(given: str | None, kind: str) -> str:
    """The endpoint of the option that names a compositor's `kind` socket (control, ingest, telemetry), or that socket
    of this user's one running compositor; ConfigError if none or several run, or for an abstract socket."""
    if not given:
        return find_endpoint(kind)
    check_endpoint(given, f"{KINDS[kind]} {given}")
    return given


def control_endpoint(args: argparse.Namespace) -> str:
    """--control, or the control socket of this user's one running compositor (ConfigError if none or several)."""
    return endpoint(args.control, "control")
