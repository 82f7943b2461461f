"""The compositor and its clients: `hmdrt run` (the daemon), `hmdrt status`, `hmdrt ctl` (any control command),
`hmdrt watch` (the live page) and `hmdrt keys` (CURVE keypairs for [security] and its clients)."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import textwrap
import threading
import time
from itertools import chain
from pathlib import Path

from hmdrt.bus.local import check_private, runtime_dir
from hmdrt.cli.common import (
    UNTIL,
    client_keys,
    control_endpoint,
    control_options,
    count,
    endpoint,
    key_options,
    seconds,
    stop_on_signals,
    write_json,
)
from hmdrt.compositor.commands import COMMANDS, Stats, Status, from_words, to_request
from hmdrt.compositor.startup import Startup
from hmdrt.console.progress import StatusLine
from hmdrt.errors import HmdrtError
from hmdrt.files.atomic import check_writable
from hmdrt.files.resources import run_config
from hmdrt.telemetry import verdict
from hmdrt.telemetry.verdict import ms


def cmd_run(args: argparse.Namespace) -> int:
    """Run the compositor daemon until stopped, the frame count or the duration; write the run report."""
    import msgspec

    from hmdrt.compositor.config import load_config
    from hmdrt.compositor.daemon import Compositor

    config = load_config(
        run_config(args.config),
        frames=args.frames,
        duration_s=args.duration,
        virtual_time=True if args.virtual_time else None,
    )
    if args.frames_log:
        output = msgspec.structs.replace(config.output, frames_log=args.frames_log)
        config = msgspec.structs.replace(config, output=output)
    report_path = args.report or config.output.report
    if report_path:
        check_writable(Path(report_path).parent)
    stop = stop_on_signals()  # before the start-up, so a SIGTERM during it still ends with a report
    reloads = threading.Event()
    signal.signal(signal.SIGHUP, lambda *_: reloads.set())
    startup = Startup()
    with StatusLine(lambda _: f"starting: {startup.now()} (a first run compiles for half a minute or more)"):
        compositor = Compositor(config, startup=startup)
    if reloads.is_set():
        compositor.reload()
    stop_relay = threading.Thread(target=lambda: (stop.wait(), compositor.stop.set()), daemon=True)
    stop_relay.start()
    signal.signal(signal.SIGHUP, lambda *_: compositor.reload())
    endpoints = compositor.status()["endpoints"]
    print(
        f"hmdrt run {args.config}: {compositor.session.spec} on {config.scene} at {compositor.session.profile.name} "
        f"({compositor.session.profile.refresh_hz:g} Hz{', virtual time' if config.run.virtual_time else ''}); "
        f"started: {startup.summary()}; control {endpoints['control']}",
        flush=True,
    )
    try:
        with StatusLine(lambda _: _run_status(compositor.summary())):
            report = compositor.run()
    finally:
        compositor.close()
    saved = _save_report(report_path, report) if report_path else ""
    print(
        f"{report['vsyncs']} VSyncs: {report['presented']} frames shown ({report['late']} late), "
        f"{report['re_presented']} repeated, {report['dropped']} dropped; frame p99 {ms(report['frame_ms']['p99'])}"
        + _gaze_error(report.get("gaze_error_at_photon_deg") or {})
        + f"; {verdict.line(report)}"
        + (f"; report {saved}" if saved else "")
    )
    return 0 if saved == report_path else 1


def _save_report(path: str, report: dict) -> str:
    """Write the run report to `path`, or when that fails (a full disk) to the runtime folder, else as one line of
    JSON on stderr, saying so in one line: where it is, so that the run is not lost with it."""
    try:
        write_json(path, report)
        return path
    except HmdrtError as exc:
        failed = f"hmdrt: error: {exc}; the run report is"
    folder = runtime_dir()
    fallback = folder / f"report-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}.json"
    try:
        folder.mkdir(mode=0o700, exist_ok=True)
        check_private(folder)
        write_json(fallback, report)
    except (HmdrtError, OSError):
        print(f"{failed} on the next line instead", file=sys.stderr)
        print(json.dumps(report), file=sys.stderr)
        return "on stderr"
    print(f"{failed} in {fallback} instead", file=sys.stderr)
    return str(fallback)


def _gaze_error(errors: dict) -> str:
    """The gaze error at photon time per eye shown, p95, for the end-of-run line; nothing when none resolved."""
    shown = [f"{eye} {errors[eye]['p95']}" for eye in ("left", "right") if errors.get(eye, {}).get("p95") is not None]
    return f"; gaze error p95 {', '.join(shown)} deg" if shown else ""


def _run_status(report: dict) -> str:
    """One line of a run so far, for the terminal."""
    gaze = report["latency_ms"]["gaze_to_photon"]
    return (
        f"{report['vsyncs']} VSyncs, {report['achieved_hz']:g} Hz, misses {report['miss_rate']:.1%}, "
        f"repeats {report['repeat_rate']:.1%}, gaze-to-photon p99 {ms(gaze['p99'])}"
    )


def _ask(args: argparse.Namespace, request: dict, refused: str = "") -> dict:
    """A running compositor's reply to one control request, without its "ok"; HmdrtError with its refusal."""
    from hmdrt.compositor.endpoints import request as send

    reply = send(control_endpoint(args), request, args.timeout, client_keys(args))
    if not reply.get("ok"):
        raise HmdrtError(f"{refused}{reply.get('error')}")
    reply.pop("ok")
    return reply


def cmd_status(args: argparse.Namespace) -> int:
    """Ask a running compositor for its status."""
    reply = _ask(args, to_request(Stats() if args.report else Status()), refused="the compositor refused: ")
    if args.json or args.report:
        print(json.dumps(reply.get("report", reply), indent=2))
        return 0
    print(_status_text(reply))
    return 0


def _status_text(reply: dict) -> str:
    """A compositor's status as a person reads it: what it renders and how often, the frames shown, the pacing in
    ms, the drivers and who may reach it (`--json` gives the reply itself)."""
    shown, pacing = reply["shown"], reply["pacing"]
    drivers = [
        f"{device} {status.get('state', '?')}" + (f" {status['rate_hz']:g} Hz" if status.get("rate_hz") else "")
        for device, status in sorted(reply.get("drivers", {}).items())
    ]
    devices = sorted(set(chain(*reply["devices"].values())))
    return (
        f"{reply['method']} on {reply['scene']} at {reply['profile']} ({reply['vsync_hz']:g} Hz, period "
        f"{ms(pacing['period_ns'] / 1e6)}): {shown['new']} frames on time, {shown['late']} late, {shown['repeat']} "
        f"repeated; render estimate {ms(pacing['render_estimate_ns'] / 1e6)} of a {ms(pacing['budget_ns'] / 1e6)} "
        f"budget (margin {ms(pacing['margin_ns'] / 1e6)}), {pacing['misses']} missed; "
        f"samples from {', '.join(devices) or 'no device yet'}"
        + (f"; drivers {', '.join(drivers)}" if drivers else "")
        + _access(reply)
    )


def _access(status: dict) -> str:
    """Who may reach the compositor, from its status: CURVE clients, this user (ipc://) or, on its tcp:// sockets,
    any local user."""
    security = status.get("security", {})
    if security.get("curve"):
        return f"; access: CURVE, {security['admitted']} handshakes admitted, {security['refused']} refused"
    open_to = security.get("open_to_local_users", [])
    if open_to:
        read_only = ", control read-only" if "control" in open_to else ""
        return f"; access: any local user on {', '.join(open_to)} (loopback tcp://){read_only}"
    return "; access: this user"


def cmd_ctl(args: argparse.Namespace) -> int:
    """Send one control command; a bad one is refused here with the control socket's own message."""
    command = from_words(args.command, args.args)
    reply = _ask(args, to_request(command))
    print(json.dumps(reply, indent=2) if reply else "ok")
    return 0


CTL_EXAMPLES = ("status", "set params.fovea_deg=5", "set 'method=weier16?frc=small'", "snapshot path=shown.png")


def ctl_epilog(width: int = 78) -> str:
    """`hmdrt ctl --help`'s list of commands, from their declarations (hmdrt.compositor.commands)."""
    lines = ["commands (* changes the compositor: ipc:// or CURVE clients only):"]
    for name, command in COMMANDS.items():
        text = " ".join((command.__doc__ or "").split())
        if command.takes:
            text += f" Takes {command.takes}."
        head = f"  {name}{'*' if command.mutating else ''}"
        lines.append(textwrap.fill(text, width, initial_indent=f"{head:<14}", subsequent_indent=" " * 14))
    words = (
        "ARG=VALUE: a string argument takes VALUE as it is, any other reads it as JSON; ARG.KEY=VALUE sets one "
        'entry of a table (VALUE JSON, else a string). The reply is printed as JSON ("ok" when it is empty).'
    )
    lines += ["", textwrap.fill(words, width), "", "examples:"]
    lines += [f"  hmdrt ctl {example}" for example in CTL_EXAMPLES]
    return "\n".join(lines)


def cmd_watch(args: argparse.Namespace) -> int:
    """Serve a live view of a running compositor (frames, plots, drivers, controls) until stopped, at a lower
    priority than the compositor's threads (hmdrt.priority)."""
    from hmdrt.priority import yield_cores
    from hmdrt.watch.server import WatchOptions, serve

    yield_cores(whole_process=True)  # before the server's threads start: they inherit it
    options = WatchOptions(
        control=control_endpoint(args),
        telemetry=endpoint(args.telemetry, "telemetry") if args.telemetry else "",  # "": the one status names
        bind=args.bind,
        port=args.port,
        allow_hosts=tuple(args.allow_host),
        keys=client_keys(args),
    )
    serve(
        options, lambda server: print(f"hmdrt watch: {server.url(token=True)} (read-only: {server.url()})", flush=True)
    )
    return 0


def cmd_keys(args: argparse.Namespace) -> int:
    """Write a CURVE keypair for the [security] section or a client's --server-key / --client-key."""
    from hmdrt.bus.security import write_keypair

    public, secret = write_keypair(args.dir, args.name, args.force)
    print(f"{public}: public key (share it); {secret}: secret key (mode 0600, keep it)")
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    run = sub.add_parser("run", help="run the compositor daemon on a config")
    run.add_argument("config", help="run config (.toml), e.g. configs/default.toml")
    limit = run.add_mutually_exclusive_group()
    limit.add_argument("--frames", type=count, help="stop after N VSyncs")
    limit.add_argument("--duration", type=seconds, help=UNTIL)
    run.add_argument("--virtual-time", action="store_true", help="a simulated clock, one period per frame")
    run.add_argument("--report", help="write the run report JSON here (overrides the config's)")
    run.add_argument("--frames-log", help="write every frame record here as JSON Lines (overrides the config's)")
    run.set_defaults(run=cmd_run)

    status = sub.add_parser("status", help="ask a running compositor daemon")
    status.add_argument("--json", action="store_true", help="print the status as JSON")
    status.add_argument("--report", action="store_true", help="print the run report so far (JSON)")
    control_options(status)
    status.set_defaults(run=cmd_status)

    ctl = sub.add_parser(
        "ctl",
        help="send a command to a running compositor's control socket",
        description="Send one command to a running compositor's control socket and print its reply.",
        epilog=ctl_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ctl.add_argument("command", metavar="COMMAND", help=f"one of {', '.join(COMMANDS)}")
    ctl.add_argument("args", nargs="*", metavar="ARG=VALUE", help="the command's arguments")
    control_options(ctl)
    ctl.set_defaults(run=cmd_ctl)

    watch = sub.add_parser("watch", help="serve a live view of a running compositor in the browser")
    watch.add_argument("--telemetry", help="its telemetry endpoint (default: the one its control socket names)")
    watch.add_argument(
        "--control", help="its control endpoint (default: this user's one running compositor, as for status)"
    )
    watch.add_argument("--port", type=int, default=8765, help="port to serve the page on (default 8765; 0: any free)")
    watch.add_argument(
        "--bind", default="127.0.0.1", help="address to serve on (default 127.0.0.1; others need the CURVE keys)"
    )
    watch.add_argument(
        "--allow-host", action="append", default=[], metavar="NAME", help="another Host name the page is opened by"
    )
    key_options(watch)
    watch.set_defaults(run=cmd_watch)

    keys = sub.add_parser("keys", help="write a CURVE keypair: NAME.key (public) and NAME.key_secret (secret)")
    keys.add_argument("name", help="the key's name, e.g. compositor or the client's")
    keys.add_argument("--dir", default=".", help="folder to write the two files to (default: here)")
    keys.add_argument("--force", action="store_true", help="replace an existing keypair of that name")
    keys.set_defaults(run=cmd_keys)
