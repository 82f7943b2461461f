"""Milliseconds of a `hmdrt watch` preview of both eyes at sim-cpu-640 (640x720 each), and of the full-size sRGB
encoding the frames PNGs and snapshots use.

    python bench/preview.py [--repeats 31] [--threads 1] [--against REV]

Renders one frame of the default config's scene (whitted, sim-cpu-640) with method full, then times per repeat,
on the numba threads asked for (the preview thread runs its kernels on one): a numba copy of both eyes' floats
into a reused buffer (the floor of any pass that reads them), the preview image (each eye shrunk 2x by block
means and encoded to 8-bit sRGB, hmdrt.present.encode.preview_srgb8), its JPEG (PIL, quality 80, as the
preview thread makes it), the whole preview message (hmdrt.compositor.preview.PreviewPublisher: image, JPEG and
the gaze and fovea marks) and both eyes encoded at full size (side_by_side_srgb8). With --against, the encoding
as it was at git revision REV (hmdrt/present/encode.py there, loaded beside this one) is timed in the same
repeats, each variant within a few milliseconds of the other: these machines are shared and noisy. Prints the
median (p50) and fastest of the repeats, the median of the repeats' own ratios, and the CPU.
"""

from __future__ import annotations

import argparse
import io
import statistics
import tempfile
import time
import types
from collections.abc import Callable
from pathlib import Path

import numba as nb
import numpy as np
from PIL import Image
from references import copy_rows, module_at

from hmdrt.compositor import preview
from hmdrt.evaluate.provenance import machine
from hmdrt.foveation import MethodChoice
from hmdrt.optics import get_profile
from hmdrt.present import encode
from hmdrt.scene import load_scene
from hmdrt.telemetry.report import FrameRecord
from hmdrt.trace.integrator import Whitted
from hmdrt.views import eye_cameras, render_frames, sequence_inputs

PROFILE, SCENE = "sim-cpu-640", "whitted"


def jpeg(srgb8: np.ndarray) -> bytes:
    """The preview image as the preview thread encodes it."""
    out = io.BytesIO()
    Image.fromarray(srgb8, mode="RGB").save(out, format="JPEG", quality=preview.JPEG_QUALITY)
    return out.getvalue()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=31)
    ap.add_argument("--threads", type=int, default=1, help="numba threads (default 1, as the preview thread)")
    ap.add_argument("--against", metavar="REV", help="also time the encoding at this git revision, in the same repeats")
    args = ap.parse_args()
    nb.set_num_threads(args.threads)

    profile, scene = get_profile(PROFILE), load_scene(SCENE)
    inputs, _ = sequence_inputs(scene.start, profile.period_ns, 1)
    with Whitted(scene) as tracer:
        _, images, _ = next(render_frames(MethodChoice.parse("full").make(tracer), profile, inputs, ("left", "right")))
    record = FrameRecord(0, 0, "new", 0, 0, 0, 0, 0, 0, 0, False, None, None, method="rrm")
    shown = preview._Shown(record, images, eye_cameras(profile, scene.start, ("left", "right")), None)
    publisher = preview.PreviewPublisher(types.SimpleNamespace())  # _message only: nothing is offered or published
    factor = -(-sum(image.shape[1] for image in images) // preview.MAX_WIDTH)
    height, width = images[0].shape[0], sum(image.shape[1] for image in images)
    small = np.empty((height // factor, width // factor, 3), np.uint8)
    full = np.empty((height, width, 3), np.uint8)
    flat = [image.reshape(image.shape[0], -1) for image in images]
    copies = [np.empty_like(rows) for rows in flat]

    print(f"preview of both eyes at {PROFILE} ({width}x{height}, shrunk {factor}x), {args.repeats} repeats, ", end="")
    print(f"{nb.get_num_threads()} numba threads\n  {machine()}")
    with tempfile.TemporaryDirectory() as folder:
        versions = {"now": encode}
        if args.against:
            versions[args.against] = module_at(args.against, "hmdrt/present/encode.py", Path(folder))
        tasks: dict[str, Callable[[], object]] = {
            "copy floor": lambda: [copy_rows(src, dst) for src, dst in zip(flat, copies, strict=True)],
            "jpeg": lambda: jpeg(small),
            "message now": lambda: publisher._message(shown),
        }
        for name, module in versions.items():
            tasks[f"image {name}"] = lambda m=module: m.preview_srgb8(images, factor, small)
            tasks[f"full {name}"] = lambda m=module: m.side_by_side_srgb8(images, full)
        ms: dict[str, list[float]] = {name: [] for name in tasks}
        for repeat in range(args.repeats + 1):  # the first compiles and warms up, untimed
            for name, task in tasks.items():
                start = time.perf_counter()
                task()
                if repeat:
                    ms[name].append((time.perf_counter() - start) * 1e3)
    publisher.close()
    for name in versions:
        ms[f"image + jpeg {name}"] = [a + b for a, b in zip(ms[f"image {name}"], ms["jpeg"], strict=True)]

    def row(label: str, key: str) -> None:
        print(f"  {label:<44} p50 {statistics.median(ms[key]):7.2f} ms   min {min(ms[key]):7.2f} ms")

    row("copy of both eyes' floats (floor)", "copy floor")
    row("JPEG of the preview (PIL, quality 80)", "jpeg")
    row("whole preview message now", "message now")
    for name in versions:
        row(f"preview image (shrink + sRGB), {name}", f"image {name}")
        row(f"preview encoded (image + JPEG), {name}", f"image + jpeg {name}")
        row(f"full-size side by side sRGB, {name}", f"full {name}")
    if args.against:
        for what in ("image", "image + jpeg", "full"):
            ratios = [b / a for a, b in zip(ms[f"{what} now"], ms[f"{what} {args.against}"], strict=True)]
            print(f"  {what}: {args.against} / now = {statistics.median(ratios):.2f}x (median of the repeats' ratios)")


if __name__ == "__main__":
    main()
