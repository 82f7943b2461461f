"""The hmdrt command line (DESIGN.md "Command line"). Errors reach the user as one line, never a traceback."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from hmdrt import __version__
from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.foveation import METHODS, FrameRequest, make_method
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.present.encode import linear_to_srgb8, write_png
from hmdrt.scene import load_scene
from hmdrt.spatial import gaze_direction, parse_gaze
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted


class _Parser(argparse.ArgumentParser):
    """argparse that reports a usage error in one line."""

    def error(self, message: str) -> None:
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _resolution(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise ConfigError(f"resolution must be WIDTHxHEIGHT, e.g. 640x720, got {text!r}") from None
    return w, h


def cmd_render(args: argparse.Namespace) -> int:
    """Render one frame of a scene through an HMD profile with a method; write a PNG and a stats JSON."""
    profile = get_profile(args.profile)
    if args.resolution:
        profile = profile.with_resolution(*_resolution(args.resolution))
    yaw, pitch = parse_gaze(args.gaze)
    options = {}
    if args.spp is not None:
        if args.method != "regular":
            raise ConfigError(f"--spp applies to method regular, not {args.method!r}")
        options["spp"] = args.spp
    if args.threads is not None and args.threads < 1:
        raise ConfigError(f"--threads must be at least 1, got {args.threads}")
    t0 = time.perf_counter()
    scene = load_scene(args.scene)
    with Whitted(scene, threads=args.threads) as tracer:
        method = make_method(args.method, tracer, **options)
        setup_ms = (time.perf_counter() - t0) * 1e3
        stats = FrameStats()
        gaze = gaze_direction(yaw, pitch)
        eyes = ["left", "right"] if args.eye == "both" else [args.eye]
        t1 = time.perf_counter()
        images = [
            method.render(FrameRequest(EyeCamera.for_eye(profile, scene.start, eye), gaze, 0, args.seed), stats)
            for eye in eyes
        ]
        with stats.stage("present"):
            srgb = linear_to_srgb8(np.concatenate(images, axis=1))
        ms_total = (time.perf_counter() - t1) * 1e3
    write_png(args.out, srgb)
    record = {
        "ms_total": round(ms_total, 3),
        **stats.to_dict(),
        "width": int(srgb.shape[1]),
        "height": int(srgb.shape[0]),
        "method": args.method,
        "scene": scene.name,
        "profile": profile.name,
        "eye": args.eye,
        "spp": getattr(method, "spp", 1),
        "gaze_deg": [yaw, pitch],
        "seed": args.seed,
        "triangles": scene.triangle_count,
        "threads": tracer.tracer.threads,
        "setup_ms": round(setup_ms, 3),
        "hmdrt": __version__,
    }
    if args.stats:
        try:
            Path(args.stats).parent.mkdir(parents=True, exist_ok=True)
            Path(args.stats).write_text(json.dumps(record, indent=2) + "\n")
        except OSError as exc:
            raise HmdrtError(f"cannot write {args.stats}: {exc.strerror}") from None
    rays = record["rays"]["total"]
    print(
        f"{args.out}: {record['width']}x{record['height']} {args.method} on {scene.name} ({profile.name}), "
        f"{ms_total:.1f} ms, {rays:,} rays"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="hmdrt", description="A simulated HMD runtime with foveated ray tracing.")
    parser.add_argument("--version", action="version", version=f"hmdrt {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    render = sub.add_parser("render", help="render one frame to a PNG and a stats JSON")
    render.add_argument(
        "--scene", required=True, help="built-in scene (e.g. whitted, voxel_city?size=50), .toml or mesh file"
    )
    render.add_argument(
        "--profile", required=True, help="HMD profile name (dk2, rift_s, fove0, vive_pro_eye, sim-cpu) or .toml"
    )
    render.add_argument(
        "--method",
        required=True,
        choices=sorted(METHODS),
        metavar="METHOD",
        help=f"rendering method: {', '.join(METHODS)}",
    )
    render.add_argument("--gaze", default="0,0", help="gaze YAW,PITCH in degrees, right and up positive (default 0,0)")
    render.add_argument("--spp", type=int, help="samples per pixel for method regular (default 36)")
    render.add_argument("--out", required=True, help="output PNG")
    render.add_argument("--stats", help="output stats JSON")
    render.add_argument(
        "--eye", choices=["left", "right", "both"], default="left", help="which eye (both: side by side)"
    )
    render.add_argument("--resolution", help="per-eye WIDTHxHEIGHT overriding the profile's, same field of view")
    render.add_argument("--seed", type=int, default=0, help="seed of every stochastic step (default 0)")
    render.add_argument("--threads", type=int, help=f"tracing threads (default {os.cpu_count()})")
    render.set_defaults(run=cmd_render)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
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
