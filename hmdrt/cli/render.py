"""`hmdrt render`: a frame or a sequence of a scene through an HMD profile with a method, as PNGs and stats JSON."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from hmdrt.cli.common import count, write_json
from hmdrt.errors import ConfigError
from hmdrt.files.atomic import write_atomic
from hmdrt.foveation import METHODS, MethodChoice
from hmdrt.optics import get_profile
from hmdrt.present.encode import linear_to_srgb8, write_png
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import RAY_KINDS, FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.version import __version__
from hmdrt.views import held_start, render_frames, sequence_inputs


def _record(stats: FrameStats, ms: float, width: int, height: int, method: str, scene: str) -> dict:
    return {
        "ms_total": round(ms, 3),
        **stats.to_dict(),
        "width": width,
        "height": height,
        "method": method,
        "scene": scene,
    }


def _warmup(text: str) -> int:
    """A number of warm-up frames: 0, or a count."""
    return 0 if text.strip() == "0" else count(text)


def cmd_render(args: argparse.Namespace) -> int:
    """Render a frame or a sequence of a scene through an HMD profile with a method; PNGs and stats JSON."""
    profile = get_profile(args.profile)
    if args.resolution:
        profile = profile.with_resolution_text(args.resolution, "--resolution")
    choice = MethodChoice.parse(args.method)
    if args.spp is not None:
        if choice.name != "regular":
            raise ConfigError(f"--spp applies to method regular, not {args.method!r}")
        choice = choice.with_options(spp=args.spp)
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
        # a temporal method's single frame after the history it declares (RRM: its refresh cycle), as it shows a
        # view it has been looking at; a sequence shows its start as it is, unless asked
        warmup = args.warmup if args.warmup is not None else 0 if sequence else method.warmup_frames
        inputs = held_start(inputs, warmup, profile.period_ns)
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
            bar.update()
            frame = inp.frame - warmup
            if frame < 0:
                continue
            write_png(out / f"frame_{frame:05d}.png" if sequence else out, srgb)
            records.append(
                {
                    "frame": frame,
                    "t_ns": inp.t_ns - warmup * profile.period_ns,
                    **_record(stats, ms, srgb.shape[1], srgb.shape[0], method.name, scene.name),
                }
            )
        bar.close()
    if sequence:
        write_atomic(out / "frames.jsonl", "".join(json.dumps(r) + "\n" for r in records).encode())
    summary = _summary(records) if sequence else records[0]
    summary.update(
        method_spec=str(choice),
        profile=profile.name,
        eye=args.eye,
        seed=args.seed,
        triangles=scene.triangle_count,
        threads=tracer.tracer.threads,
        setup_ms=round(setup_ms, 3),
        warmup_frames=warmup,
        hmdrt=__version__,
        spp=getattr(method, "spp", 1),
    )
    if counts is not None:
        summary["trace"] = vars(counts)
    if args.stats:
        write_json(args.stats, summary)
    where = f"{out}/ ({len(records)} frames)" if sequence else str(out)
    print(
        f"{where}: {summary['width']}x{summary['height']} {method.name} on {scene.name} ({profile.name}), "
        f"{summary['ms_total']:.1f} ms{'/frame' if sequence else ''}, {summary['rays']['total']:,} rays"
        f"{'/frame' if sequence else ''}"
        + (f", after {warmup} warm-up frames of the same view ({method.name}'s history)" if warmup else "")
    )
    return 0


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


def add_commands(sub: argparse._SubParsersAction) -> None:
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
    render.add_argument("--frames", type=count, help="render a sequence of N frames at the profile's refresh rate")
    render.add_argument(
        "--warmup",
        type=_warmup,
        help="frames of the first view rendered and not written first (default: the method's declared history for "
        "one frame, so rrm shows its whole image; 0 for a sequence)",
    )
    render.add_argument("--trace", help="native gaze/pose trace (.jsonl[.gz]) driving the sequence, or 'builtin'")
    render.add_argument(
        "--eye", choices=["left", "right", "both"], default="left", help="which eye (both: side by side)"
    )
    render.add_argument("--resolution", help="per-eye WIDTHxHEIGHT overriding the profile's, same field of view")
    render.add_argument("--seed", type=int, default=0, help="seed of every stochastic step (default 0)")
    render.add_argument("--threads", type=count, help="tracing threads (default: all cores)")
    render.set_defaults(run=cmd_render)
