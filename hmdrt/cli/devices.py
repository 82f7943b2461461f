"""Trackers and their traces: `hmdrt driver` (a device's samples onto the bus), `hmdrt emulate` (a tracker to
connect a driver to), `hmdrt record` (the bus into a native trace) and `hmdrt convert` (a trace between formats)."""

from __future__ import annotations

import argparse

import zmq

from hmdrt.bus.local import bind_endpoints, check_endpoint, ipc_path
from hmdrt.bus.security import is_loopback
from hmdrt.cli.common import UNTIL, client_keys, endpoint, key_options, seconds, stop_on_signals
from hmdrt.drivers.emulators import EMULATORS
from hmdrt.errors import ConfigError
from hmdrt.replay.convert import READER_OPTIONS, convert_trace

# make_emulator's keywords: the emulate command's options store their values under these names
EMULATOR_OPTIONS = ("host", "port", "trace", "seed", "rate_hz", "offset_deg", "noise_deg", "latency_ms")


def cmd_driver(args: argparse.Namespace) -> int:
    """Run a driver and publish its samples on the bus until stopped."""
    from hmdrt.drivers.host import DriverHost

    bus = endpoint(args.bus, "ingest") if args.bus else ""  # "": DriverHost finds it once the URL is checked
    host = DriverHost(args.url, bus, curve=client_keys(args))
    counters = host.run(stop_on_signals(), args.duration)
    print(f"{args.url}: {counters.summary()}")
    return 0


def cmd_emulate(args: argparse.Namespace) -> int:
    """Serve an emulated tracker until stopped."""
    from hmdrt.drivers.emulators import make_emulator

    emulator = make_emulator(args.device, **{name: getattr(args, name) for name in EMULATOR_OPTIONS})
    stop = stop_on_signals()
    with emulator:
        print(f"{args.device} emulator: connect with: hmdrt driver '{emulator.url}'", flush=True)
        stop.wait(args.duration)
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    """Record a device's samples from the bus into a native trace."""
    from hmdrt.replay.recorder import Recorder

    keys, context, bus = client_keys(args), None, args.bus or ""
    check_endpoint(bus, f"--bus {bus}")
    if args.connect and not bus:
        raise ConfigError("--connect needs --bus ENDPOINT, the publisher to connect to")
    if keys is not None:
        if not args.connect:
            raise ConfigError("--server-key and --client-key are for --connect (a bound recorder has no CURVE)")
        context = zmq.Context()  # the recorder makes its own socket: a context whose sockets are CURVE clients
        keys.set_defaults(context)
    elif not args.connect and not is_loopback(bus):
        raise ConfigError(f"record binds loopback only, not {bus} (a bound recorder has no CURVE)")
    if not args.connect:
        bus = bind_endpoints({"ingest": bus})["ingest"]  # by default where `hmdrt driver` finds a compositor's
    recorder = Recorder(bus, args.out, bind=not args.connect, device=args.device, context=context)
    made = ipc_path(bus) if not args.bus else None  # 0600 and removed after, as a compositor's
    if made is not None:
        made.chmod(0o600)
    try:
        print(f"recording {recorder.endpoint} to {args.out}", flush=True)
        recorder.run(stop_on_signals(), args.duration)
    finally:
        if made is not None:
            made.unlink(missing_ok=True)
    print(f"{args.out}: {recorder.summary()}")
    return 0


def cmd_convert(args: argparse.Namespace) -> int:
    """Convert a trace to native JSONL or hmdrt CSV, or export it as BIDS eye-tracking physio (replay/convert.py)."""
    options = {name: getattr(args, name) for name in READER_OPTIONS if getattr(args, name) is not None}
    done = convert_trace(args.input, args.out, force=args.force, **options)
    left_out = f"; {done.left_out} head-pose samples left out (gaze only)" if done.left_out else ""
    print(
        f"{', '.join(map(str, done.written))}: {done.samples} samples as {done.output_format} from {args.input} "
        f"({done.reading.device}, {done.reading.malformed} malformed lines skipped){left_out}"
    )
    return 0


def add_commands(sub: argparse._SubParsersAction) -> None:
    driver = sub.add_parser("driver", help="run a device driver and publish its samples on the bus")
    driver.add_argument(
        "url", help="driver URL, e.g. synthetic://?seed=1&rate=250, replay://trace.jsonl, smi://host:4444"
    )
    driver.add_argument(
        "--bus", help="the compositor's ingest endpoint (default: this user's one running compositor's, ipc://)"
    )
    driver.add_argument("--duration", type=seconds, help=UNTIL)
    key_options(driver)
    driver.set_defaults(run=cmd_driver)

    emulate = sub.add_parser("emulate", help="serve an emulated eye or head tracker for drivers to connect to")
    emulate.add_argument(
        "device", choices=EMULATORS, help="tracker protocol (razor, hatire: serial head trackers; lsl: no port)"
    )
    emulate.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1)")
    emulate.add_argument("--port", type=int, help="port (default: the device's usual one; 0 = any free port)")
    source = emulate.add_mutually_exclusive_group()
    source.add_argument("--trace", help="gaze from a recorded trace (any format `hmdrt render --trace` reads)")
    source.add_argument(
        "--synthetic", dest="seed", type=int, default=0, metavar="SEED", help="synthetic gaze of SEED (default 0)"
    )
    for flag, dest, text in (
        ("--rate", "rate_hz", "sample rate in Hz (default: the device's)"),
        ("--offset", "offset_deg", "tracker accuracy error in degrees (default 0)"),
        ("--noise", "noise_deg", "tracker precision noise in degrees (default 0)"),
        ("--latency", "latency_ms", "capture-to-send latency in ms (default: the device's)"),
    ):
        emulate.add_argument(flag, dest=dest, type=float, metavar=flag[2:].upper(), help=text)
    emulate.add_argument("--duration", type=seconds, help=UNTIL)
    emulate.set_defaults(run=cmd_emulate)

    record = sub.add_parser("record", help="record a device's gaze and pose from the bus into a native trace")
    record.add_argument("--out", required=True, help="output trace (.jsonl)")
    record.add_argument(
        "--bus", help="endpoint to bind as the ingest (default: ipc:// where `hmdrt driver` finds it, yours alone)"
    )
    record.add_argument("--connect", action="store_true", help="connect to a publisher at --bus instead of binding")
    record.add_argument("--device", help="the device to record (default: the first one heard)")
    record.add_argument("--duration", type=seconds, help=UNTIL)
    key_options(record)
    record.set_defaults(run=cmd_record)

    convert = sub.add_parser("convert", help="convert a gaze trace to native JSONL or hmdrt CSV, or export it to BIDS")
    convert.add_argument(
        "input",
        metavar="IN",
        help="a trace: .jsonl[.gz], EyeLink .asc, GazeBase, GazeBaseVR, Pupil Player or hmdrt .csv",
    )
    convert.add_argument(
        "out", metavar="OUT", help="output: .jsonl[.gz] (native), .csv[.gz] (hmdrt CSV), NAME_physio.tsv.gz (BIDS)"
    )
    convert.add_argument("--force", action="store_true", help="replace outputs that exist")
    for name, text in READER_OPTIONS.items():
        unit = "MM" if name.endswith("_mm") else "C"
        convert.add_argument(f"--{name.replace('_', '-')}", dest=name, type=float, metavar=unit, help=text)
    convert.set_defaults(run=cmd_convert)
