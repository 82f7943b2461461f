"""The hmdrt command line (docs/architecture.md, Command line). Errors reach the user as one line, never a traceback."""

from __future__ import annotations

import argparse
import json
import os
import signal
import sys
import threading
import time
from itertools import chain
from pathlib import Path

import numpy as np
import zmq
from tqdm import tqdm

from hmdrt.bus import INGEST
from hmdrt.bus.local import find_control
from hmdrt.bus.security import ClientKeys, is_loopback, write_keypair
from hmdrt.console import logs
from hmdrt.console.progress import StatusLine
from hmdrt.drivers.emulators import EMULATORS
from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.files.atomic import check_writable, write_atomic
from hmdrt.files.resources import run_config
from hmdrt.foveation import METHODS, MethodChoice
from hmdrt.optics import get_profile
from hmdrt.present.encode import linear_to_srgb8, write_png
from hmdrt.replay.convert import READER_OPTIONS, convert_trace
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import RAY_KINDS, FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.version import __version__
from hmdrt.views import render_frames, sequence_inputs

UNTIL = "stop after SEC seconds (default: until SIGINT/SIGTERM)"
# make_emulator's keywords: the emulate command's options store their values under these names
EMULATOR_OPTIONS = ("host", "port", "trace", "seed", "rate_hz", "offset_deg", "noise_deg", "latency_ms")


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line."""

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _write_json(path: str | Path, record: dict) -> None:
    write_atomic(path, (json.dumps(record, indent=2) + "\n").encode())


def _record(stats: FrameStats, ms: float, width: int, height: int, method: str, scene: str) -> dict:
    return {
        "ms_total": round(ms, 3),
        **stats.to_dict(),
        "width": width,
        "height": height,
        "method": method,
        "scene": scene,
    }


def _summary(records: list[dict]) -> dict:
    """The per-frame means of a sequence, with the render stats keys of docs/architecture.md."""
    n = len(records)
    stages: dict[str, float] = {}
    for r in records:
        for k, v in r["stages_ms"].items():
            stages[k] = stages.get(k, 0.0) + v / n
    rays = {k: round(sum(r["rays"][k] for r in records) / n) for k in (*RAY_KINDS, "total")}
    return {
        **records[-1],
        "ms_total": round(sum(r["ms_total"] for r in records) / n, 3),
        "stages_ms": {k: round(v, 3) for k, v in stages.items()},
        "rays": rays,
        "stages_run": list(stages),
        "frames": n,
    }


def cmd_render(args: argparse.Namespace) -> int:
    """Render a frame or a sequence of a scene through an HMD profile with a method; PNGs and stats JSON."""
    profile = get_profile(args.profile)
    if args.resolution:
        profile = profile.with_resolution_text(args.resolution)
    choice = MethodChoice.parse(args.method)
    if args.spp is not None:
        if choice.name != "regular":
            raise ConfigError(f"--spp applies to method regular, not {args.method!r}")
        choice = choice.with_options(spp=args.spp)
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads must be at least 1, got {args.threads}")
    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be at least 1, got {args.frames}")
    sequence = args.frames is not None or args.trace is not None
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    inputs, counts = sequence_inputs(
        scene.start, profile.period_ns, args.frames, trace=args.trace, gaze=args.gaze, seed=args.seed
    )
    eyes = ("left", "right") if args.eye == "both" else (args.eye,)
    records, out = [], Path(args.out)
    with Whitted(scene, threads=args.threads) as tracer:
        method = choice.make(tracer)
        setup_ms = (time.perf_counter() - t0) * 1e3
        frames = render_frames(method, profile, inputs, eyes, args.seed)
        bar = tqdm(total=len(inputs), unit="frame", disable=not sequence or None, file=sys.stderr)
        while True:
            t1 = time.perf_counter()
            try:
                inp, images, stats = next(frames)
            except StopIteration:
                break
            with stats.stage("present"):
                srgb = linear_to_srgb8(np.concatenate(images, axis=1))
            ms = (time.perf_counter() - t1) * 1e3
            write_png(out / f"frame_{inp.frame:05d}.png" if sequence else out, srgb)
            records.append(
                {
                    "frame": inp.frame,
                    "t_ns": inp.t_ns,
                    **_record(stats, ms, srgb.shape[1], srgb.shape[0], method.name, scene.name),
                }
            )
            bar.update()
        bar.close()
    if sequence:
        try:
            with (out / "frames.jsonl").open("w") as f:
                f.writelines(json.dumps(r) + "\n" for r in records)
        except OSError as exc:
            raise HmdrtError(f"cannot write {out / 'frames.jsonl'}: {exc.strerror}") from None
    summary = _summary(records) if sequence else records[0]
    summary.update(
        method_spec=str(choice),
        profile=profile.name,
        eye=args.eye,
        seed=args.seed,
        triangles=scene.triangle_count,
        threads=tracer.tracer.threads,
        setup_ms=round(setup_ms, 3),
        hmdrt=__version__,
        spp=getattr(method, "spp", 1),
    )
    if counts is not None:
        summary["trace"] = vars(counts)
    if args.stats:
        _write_json(args.stats, summary)
    where = f"{out}/ ({len(records)} frames)" if sequence else str(out)
    print(
        f"{where}: {summary['width']}x{summary['height']} {method.name} on {scene.name} ({profile.name}), "
        f"{summary['ms_total']:.1f} ms{'/frame' if sequence else ''}, {summary['rays']['total']:,} rays"
        f"{'/frame' if sequence else ''}"
    )
    return 0


def _stop_on_signals() -> threading.Event:
    """An event set by SIGINT or SIGTERM, so long-running commands stop cleanly."""
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    return stop


def _duration(args: argparse.Namespace) -> float | None:
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f"--duration must be positive, got {args.duration}")
    return args.duration


def cmd_driver(args: argparse.Namespace) -> int:
    """Run a driver and publish its samples on the bus until stopped."""
    from hmdrt.drivers.host import DriverHost

    duration = _duration(args)
    host = DriverHost(args.url, args.bus, curve=_client_keys(args))
    counters = host.run(_stop_on_signals(), duration)
    print(f"{args.url}: {counters.summary()}")
    return 0


def cmd_emulate(args: argparse.Namespace) -> int:
    """Serve an emulated tracker until stopped."""
    from hmdrt.drivers.emulators import make_emulator

    duration = _duration(args)
    emulator = make_emulator(args.device, **{name: getattr(args, name) for name in EMULATOR_OPTIONS})
    stop = _stop_on_signals()
    with emulator:
        print(f"{args.device} emulator: connect with: hmdrt driver '{emulator.url}'", flush=True)
        stop.wait(duration)
    return 0


def cmd_record(args: argparse.Namespace) -> int:
    """Record a device's samples from the bus into a native trace."""
    from hmdrt.replay.recorder import Recorder

    duration = _duration(args)
    keys, context = _client_keys(args), None
    if keys is not None:
        if not args.connect:
            raise ConfigError("--server-key and --client-key are for --connect (a bound recorder has no CURVE)")
        context = zmq.Context()  # the recorder makes its own socket: a context whose sockets are CURVE clients
        keys.set_defaults(context)
    elif not args.connect and not is_loopback(args.bus):
        raise ConfigError(f"record binds loopback only, not {args.bus} (a bound recorder has no CURVE)")
    recorder = Recorder(args.bus, args.out, bind=not args.connect, device=args.device, context=context)
    print(f"recording {recorder.endpoint} to {args.out}", flush=True)
    recorder.run(_stop_on_signals(), duration)
    print(f"{args.out}: {recorder.summary()}")
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    """Run the compositor daemon until stopped, the frame count or the duration; write the run report."""
    import msgspec

    from hmdrt.compositor.config import load_config
    from hmdrt.compositor.daemon import Compositor

    if args.frames is not None and args.frames < 1:
        raise ConfigError(f"--frames must be at least 1, got {args.frames}")
    config = load_config(
        run_config(args.config),
        frames=args.frames,
        duration_s=_duration(args),
        virtual_time=True if args.virtual_time else None,
    )
    if args.frames_log:
        output = msgspec.structs.replace(config.output, frames_log=args.frames_log)
        config = msgspec.structs.replace(config, output=output)
    report_path = args.report or config.output.report
    if report_path:
        check_writable(Path(report_path).parent)
    stop = _stop_on_signals()  # before the start-up, so a SIGTERM during it still ends with a report
    reloads = threading.Event()
    signal.signal(signal.SIGHUP, lambda *_: reloads.set())
    with StatusLine(
        lambda s: f"starting: compiling kernels (about a minute on a first run), connecting drivers: {s:.0f} s"
    ):
        compositor = Compositor(config)
    if reloads.is_set():
        compositor.reload()
    stop_relay = threading.Thread(target=lambda: (stop.wait(), compositor.stop.set()), daemon=True)
    stop_relay.start()
    signal.signal(signal.SIGHUP, lambda *_: compositor.reload())
    endpoints = compositor.status()["endpoints"]
    print(
        f"hmdrt run {args.config}: {compositor.session.spec} on {config.scene} at {compositor.session.profile.name} "
        f"({compositor.session.profile.refresh_hz:g} Hz{', virtual time' if config.run.virtual_time else ''}); "
        f"control {endpoints['control']}",
        flush=True,
    )
    try:
        with StatusLine(lambda _: _run_status(compositor.summary())):
            report = compositor.run()
    finally:
        compositor.close()
    if report_path:
        _write_json(report_path, report)
    gaze, levels = report["latency_ms"]["gaze_to_photon"], report["controller_level"]
    print(
        f"{report['vsyncs']} VSyncs: {report['presented']} frames shown ({report['late']} late), "
        f"{report['re_presented']} repeated, {report['dropped']} dropped; miss rate {report['miss_rate']:.1%}; "
        f"frame p99 {report['frame_ms']['p99']} ms; gaze-to-photon p99 {gaze['p99']} ms"
        + (f"; controller level p50 {levels['p50']}" if levels and "controller" in report else "")
        + (f"; report {report_path}" if report_path else "")
    )
    return 0


def _run_status(report: dict) -> str:
    """One line of a run so far, for the terminal."""
    gaze = report["latency_ms"]["gaze_to_photon"]
    return (
        f"{report['vsyncs']} VSyncs, {report['achieved_hz']:g} Hz, misses {report['miss_rate']:.1%}, "
        f"repeats {report['repeat_rate']:.1%}, gaze-to-photon p99 {gaze['p99']} ms"
    )


def cmd_status(args: argparse.Namespace) -> int:
    """Ask a running compositor for its status."""
    from hmdrt.compositor.endpoints import request

    endpoint = args.control or find_control()
    reply = request(endpoint, {"cmd": "stats" if args.report else "status"}, args.timeout, _client_keys(args))
    if not reply.get("ok"):
        raise HmdrtError(f"the compositor refused: {reply.get('error')}")
    reply.pop("ok")
    if args.json or args.report:
        print(json.dumps(reply.get("report", reply), indent=2))
        return 0
    shown = reply["shown"]
    pacing = reply["pacing"]
    print(
        f"{reply['method']} on {reply['scene']} at {reply['profile']} ({reply['vsync_hz']:g} Hz): "
        f"{shown['new']} on time, {shown['late']} late, {shown['repeat']} repeated; "
        f"devices {', '.join(sorted(set(chain(*reply['devices'].values())))) or 'none'}; pacing {json.dumps(pacing)}"
        + _access(reply)
    )
    return 0


def _access(status: dict) -> str:
    """Who may reach the compositor, from its status: CURVE clients, this user (ipc://) or any local user (tcp://)."""
    security = status.get("security", {})
    if security.get("curve"):
        return f"; access: CURVE, {security['admitted']} handshakes admitted, {security['refused']} refused"
    if status["endpoints"]["control"].startswith("tcp://"):
        return "; access: loopback, control read-only"
    return "; access: this user"


def cmd_keys(args: argparse.Namespace) -> int:
    """Write a CURVE keypair for the [security] section or a client's --server-key / --client-key."""
    public, secret = write_keypair(args.dir, args.name, args.force)
    print(f"{public}: public key (share it); {secret}: secret key (mode 0600, keep it)")
    return 0


def cmd_watch(args: argparse.Namespace) -> int:
    """Serve a live view of a running compositor (frames, plots, drivers, controls) until stopped."""
    from hmdrt.watch.server import WatchOptions, serve

    options = WatchOptions(
        control=args.control or find_control(),
        telemetry=args.telemetry or "",
        bind=args.bind,
        port=args.port,
        allow_hosts=tuple(args.allow_host),
        keys=_client_keys(args),
    )
    serve(
        options, lambda server: print(f"hmdrt watch: {server.url(token=True)} (read-only: {server.url()})", flush=True)
    )
    return 0


def _client_keys(args: argparse.Namespace) -> ClientKeys | None:
    return ClientKeys.from_options(args.server_key, args.client_key)


def _cluster_spec(text: str) -> str:
    """--cluster's value, checked by hmdrt.evaluate.cluster (imported only when the option is given)."""
    from hmdrt.evaluate.cluster import cluster_spec

    return cluster_spec(text)


def _key_options(parser: argparse.ArgumentParser) -> None:
    """--server-key and --client-key: connect as a CURVE client to a compositor with [security]."""
    parser.add_argument(
        "--server-key", metavar="PUBLIC_KEY_FILE", help="the compositor's public key (NAME.key): connect with CURVE"
    )
    parser.add_argument(
        "--client-key", metavar="SECRET_KEY_FILE", help="this client's secret key (NAME.key_secret), on its allow-list"
    )


def cmd_eval(args: argparse.Namespace) -> int:
    """Render every cell of an eval config, score it against the ground truth, write results and plots."""
    from hmdrt.evaluate.config import load_eval_config
    from hmdrt.evaluate.partial import PartialResults
    from hmdrt.evaluate.results import table, write_results
    from hmdrt.evaluate.runner import evaluate
    from hmdrt.evaluate.tables import paper_tables

    config = load_eval_config(args.config, frames=args.frames, warmup_frames=args.warmup_frames)
    out = Path(args.resume or args.out)
    check_writable(out)
    if args.cluster:
        from hmdrt.evaluate import cluster

        with cluster.connect(args.cluster) as client:
            print(f"hmdrt eval: Dask dashboard at {client.dashboard_link}", file=sys.stderr)
            evaluation = cluster.evaluate(config, client, PartialResults(out, config, resume=bool(args.resume)))
    else:
        evaluation = evaluate(config, saved=PartialResults(out, config, resume=bool(args.resume)))
    written = write_results(evaluation, config, out, with_plots=not args.no_plots)
    print(table(evaluation))
    if config.tables:
        print(paper_tables(evaluation.rows, config.tables))
    print(f"wrote {len(written)} files to {out}: {', '.join(p.name for p in written)}")
    return 0


def cmd_export_perfetto(args: argparse.Namespace) -> int:
    """Write a frames log as a timeline in Chrome trace-event JSON, for Perfetto and chrome://tracing."""
    from hmdrt.telemetry.frames_log import read_frames_log
    from hmdrt.telemetry.perfetto import write_trace

    reading = read_frames_log(args.frames_log)
    events = write_trace(reading, args.out)
    print(f"{args.out}: {events} trace events of {len(reading.records)} VSyncs (open in ui.perfetto.dev)")
    return 0


def cmd_report_plot(args: argparse.Namespace) -> int:
    """Plot a run's frame times, misses, latency and controller level from its frames log or run report."""
    from hmdrt.telemetry.plot import plot_run

    written, note = plot_run(args.input, args.out)
    print(f"wrote {len(written)} files to {args.out}: {', '.join(p.name for p in written)}")
    if note:
        print(f"{args.input}: {note}")
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


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="hmdrt", description="A simulated HMD runtime with foveated ray tracing.")
    parser.add_argument("--version", action="version", version=f"hmdrt {__version__}")
    parser.add_argument(
        "--log-level", choices=logs.LEVELS, default="warning", help="log records shown on stderr (default warning)"
    )
    parser.add_argument(
        "-v", "--verbose", dest="log_level", action="store_const", const="info", help="the same as --log-level info"
    )
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    render = sub.add_parser("render", help="render a frame or a sequence to PNG and a stats JSON")
    render.add_argument(
        "--scene", required=True, help="built-in scene (e.g. whitted, voxel_city?size=50), .toml or mesh"
    )
    render.add_argument(
        "--profile", required=True, help="HMD profile (dk2, rift_s, fove0, vive_pro_eye, sim-cpu, sim-cpu-640) or .toml"
    )
    render.add_argument(
        "--method",
        required=True,
        metavar="METHOD",
        help=f"rendering method, with options as in weier16?frc=small: {', '.join(METHODS)}",
    )
    render.add_argument("--gaze", default="0,0", help="gaze YAW,PITCH in degrees, right and up positive (default 0,0)")
    render.add_argument("--spp", type=int, help="samples per pixel for method regular (default 36)")
    render.add_argument("--out", required=True, help="output PNG; with --frames or --trace, an output folder")
    render.add_argument("--stats", help="output stats JSON (for a sequence: per-frame means)")
    render.add_argument("--frames", type=int, help="render a sequence of N frames at the profile's refresh rate")
    render.add_argument("--trace", help="native gaze/pose trace (.jsonl[.gz]) driving the sequence, or 'builtin'")
    render.add_argument(
        "--eye", choices=["left", "right", "both"], default="left", help="which eye (both: side by side)"
    )
    render.add_argument("--resolution", help="per-eye WIDTHxHEIGHT overriding the profile's, same field of view")
    render.add_argument("--seed", type=int, default=0, help="seed of every stochastic step (default 0)")
    render.add_argument("--threads", type=int, help=f"tracing threads (default {os.cpu_count()})")
    render.set_defaults(run=cmd_render)
    driver = sub.add_parser("driver", help="run a device driver and publish its samples on the bus")
    driver.add_argument(
        "url", help="driver URL, e.g. synthetic://?seed=1&rate=250, replay://trace.jsonl, smi://host:4444"
    )
    driver.add_argument("--bus", default=INGEST, help=f"the compositor's ingest endpoint (default {INGEST})")
    driver.add_argument("--duration", type=float, help=UNTIL)
    _key_options(driver)
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
    emulate.add_argument("--duration", type=float, help=UNTIL)
    emulate.set_defaults(run=cmd_emulate)
    run = sub.add_parser("run", help="run the compositor daemon on a config")
    run.add_argument("config", help="run config (.toml), e.g. configs/default.toml")
    limit = run.add_mutually_exclusive_group()
    limit.add_argument("--frames", type=int, help="stop after N VSyncs")
    limit.add_argument("--duration", type=float, help=UNTIL)
    run.add_argument("--virtual-time", action="store_true", help="a simulated clock, one period per frame")
    run.add_argument("--report", help="write the run report JSON here (overrides the config's)")
    run.add_argument("--frames-log", help="write every frame record here as JSON Lines (overrides the config's)")
    run.set_defaults(run=cmd_run)
    status = sub.add_parser("status", help="ask a running compositor daemon")
    status.add_argument(
        "--control",
        help="its control endpoint (default: this user's one running compositor, ipc:// in $XDG_RUNTIME_DIR/hmdrt)",
    )
    status.add_argument("--json", action="store_true", help="print the status as JSON")
    status.add_argument("--report", action="store_true", help="print the run report so far (JSON)")
    status.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for an answer (default 2)")
    _key_options(status)
    status.set_defaults(run=cmd_status)
    evaluation = sub.add_parser("eval", help="measure error against run time of methods over scenes and traces")
    evaluation.add_argument("config", help="eval config (.toml), e.g. configs/eval/quick.toml")
    where = evaluation.add_mutually_exclusive_group(required=True)
    where.add_argument("--out", help="output folder: results.csv, results.json, plots")
    where.add_argument("--resume", metavar="DIR", help="go on with an earlier run in DIR, keeping its finished cells")
    evaluation.add_argument("--frames", type=int, help="frames per cell (overrides the config's)")
    evaluation.add_argument("--warmup-frames", type=int, help="frames rendered before timing (overrides the config's)")
    evaluation.add_argument("--no-plots", action="store_true", help="write the results only")
    evaluation.add_argument(
        "--cluster",
        type=_cluster_spec,
        help="run on Dask: local:N (N worker processes here) or tcp://HOST:8786 (a scheduler); docs/cluster.md",
    )
    evaluation.set_defaults(run=cmd_eval)
    record = sub.add_parser("record", help="record a device's gaze and pose from the bus into a native trace")
    record.add_argument("--out", required=True, help="output trace (.jsonl)")
    record.add_argument("--bus", default=INGEST, help=f"endpoint to bind as the ingest (default {INGEST})")
    record.add_argument("--connect", action="store_true", help="connect to a publisher at --bus instead of binding")
    record.add_argument("--device", help="the device to record (default: the first one heard)")
    record.add_argument("--duration", type=float, help=UNTIL)
    _key_options(record)
    record.set_defaults(run=cmd_record)
    keys = sub.add_parser("keys", help="write a CURVE keypair: NAME.key (public) and NAME.key_secret (secret)")
    keys.add_argument("name", help="the key's name, e.g. compositor or the client's")
    keys.add_argument("--dir", default=".", help="folder to write the two files to (default: here)")
    keys.add_argument("--force", action="store_true", help="replace an existing keypair of that name")
    keys.set_defaults(run=cmd_keys)
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
    _key_options(watch)
    watch.set_defaults(run=cmd_watch)
    export = sub.add_parser("export", help="convert a run's frames log for other tools")
    formats = export.add_subparsers(dest="export_format", required=True, parser_class=_Parser)
    perfetto = formats.add_parser("perfetto", help="a timeline in Chrome trace-event JSON (Perfetto, chrome://tracing)")
    perfetto.add_argument("frames_log", metavar="FRAMES.jsonl", help="a frames log ([output] frames_log)")
    perfetto.add_argument("--out", required=True, help="output trace JSON, e.g. run.json")
    perfetto.set_defaults(run=cmd_export_perfetto)
    report = sub.add_parser("report", help="look at a finished run")
    reports = report.add_subparsers(dest="report_action", required=True, parser_class=_Parser)
    plot = reports.add_parser("plot", help="plot frame times, misses, latency and controller level as PNGs")
    plot.add_argument(
        "input", metavar="FRAMES.jsonl|REPORT.json", help="a frames log (.jsonl) or a run report (only percentiles)"
    )
    plot.add_argument("--out", required=True, help="output folder for the PNGs")
    plot.set_defaults(run=cmd_report_plot)
    convert = sub.add_parser("convert", help="convert a gaze trace to native JSONL or hmdrt CSV, or export it to BIDS")
    convert.add_argument(
        "input", metavar="IN", help="a trace: .jsonl[.gz], EyeLink .asc, GazeBaseVR, Pupil Player or hmdrt .csv"
    )
    convert.add_argument(
        "out", metavar="OUT", help="output: .jsonl[.gz] (native), .csv[.gz] (hmdrt CSV), NAME_physio.tsv.gz (BIDS)"
    )
    convert.add_argument("--force", action="store_true", help="replace outputs that exist")
    for name, text in READER_OPTIONS.items():
        unit = "MM" if name.endswith("_mm") else "C"
        convert.add_argument(f"--{name.replace('_', '-')}", dest=name, type=float, metavar=unit, help=text)
    convert.set_defaults(run=cmd_convert)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
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
