"""kim2021 Figure 6's comparison: kim21 with pixel reuse against the same frames rendered without it, PSNR per
central band (sRGB) between the two images, the share of central pixels reused and ms per frame, on the slow
traces of configs/eval/kim21_reuse.toml (rift_s optics at 640x720, frames 16-35 scored).

    python bench/kim21_reuse.py whitted slow_pursuit
    python bench/kim21_reuse.py tunnel_maps slow_head 'kim21,kim21?tau_reuse=2'
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from hmdrt.evaluate.quality import band_psnr, srgb_encode
from hmdrt.foveation import make_method
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import eye_cameras, frame_requests, sequence_inputs

FRAMES, WARMUP = 36, 16
BANDS = ("fovea", "parafovea", "perifovea", "near_periphery")
TRACES = Path(__file__).resolve().parents[1] / "configs" / "eval" / "traces"


def _render(spec: str, tracer: Whitted, requests: list) -> tuple[list, list[float], list[float]]:
    """The scored frames (sRGB), their reuse fractions and ms."""
    method = make_method(spec, tracer)
    images, reused, ms = [], [], []
    for k, request in enumerate(requests):
        stats = FrameStats()
        t = time.perf_counter()
        image = method.render(request, stats)
        elapsed = (time.perf_counter() - t) * 1e3
        if k >= WARMUP:
            images.append(srgb_encode(image.copy()))
            reused.append(stats.metrics.get("reuse_fraction", 0.0))
            ms.append(elapsed)
    return images, reused, ms


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("scene")
    parser.add_argument("trace", choices=("slow_pursuit", "slow_head"))
    parser.add_argument("specs", nargs="?", default="kim21", help="comma-separated kim21 specs with reuse on")
    args = parser.parse_args()
    scene = load_scene(args.scene)
    profile = get_profile("rift_s").with_resolution(640, 720)
    inputs, _ = sequence_inputs(scene.start, profile.period_ns, FRAMES, str(TRACES / f"kim21_{args.trace}.jsonl"))
    requests = [frame_requests(i, eye_cameras(profile, i.pose, ("left",)), 0)[0] for i in inputs]
    eccentricities = [r.camera.eccentricity(r.gaze) for r in requests[WARMUP:]]
    with Whitted(scene) as tracer:
        off_images, _, off_ms = _render("kim21?reuse=false", tracer, requests)
        for spec in args.specs.split(","):
            images, reused, ms = _render(spec, tracer, requests)
            psnrs = [band_psnr(a, b, e) for a, b, e in zip(images, off_images, eccentricities, strict=True)]
            bands = []
            for band in BANDS:
                values = [p[band] for p in psnrs if math.isfinite(p[band])]
                bands.append(f"{band} {np.mean(values) if values else math.inf:.1f} dB")
            print(
                f"{args.scene} {args.trace} {spec}: reused {100 * np.mean(reused):.1f}% of the central pixels; "
                f"against reuse off {', '.join(bands)}; {np.median(ms):.1f} ms against {np.median(off_ms):.1f}"
            )


if __name__ == "__main__":
    main()
