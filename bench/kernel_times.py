"""Named kernels' time inside a method's frames: what a change to one kernel saves where it runs.

    python bench/kernel_times.py SPEC MODULE:NAME [MODULE:NAME ...] [--scene whitted] [--profile rift_s]
                                 [--frames 10] [--warmup 3] [--trace builtin] [--gaze 0,0]

A spy takes the place of each MODULE's attribute NAME, a function or Class.method that the method calls, and times
every call; `MODULE:dynamic` (hmdrt.kernels.schedule.dynamic, as a module imported it) counts each call under the
kernel it runs, and `MODULE:NAME[K]` counts calls apart by their positional argument K (a pyramid level, say). The
method renders --frames frames of one eye; the first --warmup (compiles, an empty history) are left out; each row is
a kernel's calls per frame, its median call and its time per frame.

A kernel timed alone on captured inputs can run faster or slower than in the frames it belongs to
(docs/performance.md, "Measuring on a shared machine"), so to compare two versions run this in each one's checkout,
alternating, with the same arguments:

    git worktree add /tmp/before HEAD~1
    cd /tmp/before && PYTHONPATH=/tmp/before python /path/to/bench/kernel_times.py weier16 \\
        hmdrt.foveation.weier16.method:dynamic
"""

from __future__ import annotations

import argparse
import importlib
import re
import statistics
import time
from collections import defaultdict
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from references import frame_arguments, left_eye_requests

from hmdrt.evaluate.provenance import stamp
from hmdrt.foveation import make_method
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

TARGET = re.compile(r"(?P<module>[\w.]+):(?P<name>\w+(?:\.\w+)?)(?:\[(?P<arg>\d+)\])?")


class Target(NamedTuple):
    """A spied attribute: the object holding it (a module or a class), its name, the label its calls are counted
    under and the positional argument (or None) that splits them."""

    owner: object
    name: str
    label: str
    split: int | None


def parse_target(text: str) -> Target:
    """MODULE:NAME, MODULE:Class.method or either with [K], imported; ValueError for anything else."""
    found = TARGET.fullmatch(text)
    if found is None:
        raise ValueError(f"{text!r}: expected MODULE:NAME, MODULE:Class.method, either with [K]")
    owner: object = importlib.import_module(found["module"])
    *classes, name = found["name"].split(".")
    for cls in classes:
        owner = getattr(owner, cls)
    if not callable(getattr(owner, name, None)):
        raise ValueError(f"{text!r}: {found['module']} has no callable {found['name']}")
    split = None if found["arg"] is None else int(found["arg"])
    return Target(owner, name, f"{found['module'].rsplit('.', 1)[-1]}.{found['name']}", split)


def spy(target: Target, calls: dict[str, list[float]]) -> Callable[[], None]:
    """Times every call of the target into calls[label] (ms); returns what puts the original back."""
    original = getattr(target.owner, target.name)

    def timed(*args, **kwargs):
        label = target.label
        if target.name == "dynamic" and args:
            label += f":{getattr(args[0], '__name__', args[0])}"
        if target.split is not None and len(args) > target.split:
            label += f"[{args[target.split]}]"
        start = time.perf_counter()
        try:
            return original(*args, **kwargs)
        finally:
            calls[label].append((time.perf_counter() - start) * 1e3)

    setattr(target.owner, target.name, timed)
    return lambda: setattr(target.owner, target.name, original)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spec", help="the method, as the other benches take it (weier18?dof=none)")
    ap.add_argument("targets", nargs="+", help="MODULE:NAME, MODULE:Class.method, either with [K]")
    frame_arguments(ap, 10, 3)
    args = ap.parse_args()
    if args.frames <= args.warmup:
        ap.error("--frames must exceed --warmup")
    try:
        targets = [parse_target(text) for text in args.targets]
    except (ValueError, ImportError, AttributeError) as exc:
        ap.error(str(exc))

    scene, profile = load_scene(args.scene), get_profile(args.profile)
    requests = left_eye_requests(scene, profile, args.frames, args.trace, args.gaze)
    calls: dict[str, list[float]] = defaultdict(list)
    restore = [spy(target, calls) for target in targets]
    try:
        with Whitted(scene, None) as tracer:
            method = make_method(args.spec, tracer)
            out = np.empty((profile.height, profile.width, 3), np.float32)
            for k, request in enumerate(requests):
                if k == args.warmup:
                    calls.clear()
                method.render(request, FrameStats(), out)
    finally:
        for undo in restore:
            undo()

    frames = args.frames - args.warmup
    where = stamp()
    view = "built-in head path" if args.trace else "still view"
    print(
        f"{args.spec} on {args.scene} at {args.profile}, {view}, {frames} frames after {args.warmup}: "
        f"{where['date']}, {where['commit']}, {where['machine']}"
    )
    print(f"  {'kernel':50s} {'calls/frame':>11s} {'median ms':>10s} {'ms/frame':>9s}")
    for label, times in calls.items():  # in the order of their first calls
        print(f"  {label:50s} {len(times) / frames:11.1f} {statistics.median(times):10.3f} {sum(times) / frames:9.3f}")


if __name__ == "__main__":
    main()
