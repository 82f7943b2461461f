"""Seconds from `hmdrt run` to its first VSync on a fresh install, each start-up step's time, and the kernels that
took longest to compile.

    python bench/first_start.py [--config configs/default.toml] [--top 12] [--repeats 1] [--json PATH]

Runs the compositor for 2 s in a subprocess whose numba cache is a new, empty folder (NUMBA_CACHE_DIR: an editable
install otherwise caches beside the sources, in __pycache__, and a second run would load it), as a first run does.
The first VSync is timed from the command to the "started:" line, which the compositor prints as its VSync clock
starts (the first VSync 50 ms later, daemon.FIRST_PRESENT_NS). numba's compile events give each kernel's CPU
seconds, not counting the kernels it compiled on the way, and which kernels were compiled after the first VSync
(none should be: a compile there stalls the frame it happens in). These machines are shared: the load average at
the start is printed, and CPU seconds vary less with it than the wall time does.
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections import defaultdict
from pathlib import Path

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

ROOT = Path(__file__).resolve().parent.parent
FIRST_PRESENT_S = 0.05  # hmdrt.compositor.daemon.FIRST_PRESENT_NS: the first VSync after the "started:" line
STEP = re.compile(r"(.+) (\d+(?:\.\d+)?) s")


def child(records: str, argv: list[str]) -> int:
    """`hmdrt` with `argv`, numba's compile events recorded: each kernel compiled (module.name), its CPU seconds
    less those of the kernels it compiled on the way, and when it ended (time.monotonic), written to `records` as
    JSON when the process exits."""
    import numba.core.event as ev

    compiles: list[dict] = []
    frames = threading.local()  # per thread: [CPU time at start, CPU seconds of nested compiles] of open compiles

    class Compiles(ev.Listener):
        def on_start(self, event: ev.Event) -> None:
            if not hasattr(frames, "open"):
                frames.open = []
            frames.open.append([time.thread_time(), 0.0])

        def on_end(self, event: ev.Event) -> None:
            began, nested = frames.open.pop()
            spent = time.thread_time() - began
            if frames.open:
                frames.open[-1][1] += spent
            f = event.data["dispatcher"].py_func
            compiles.append(
                {"kernel": f"{f.__module__}.{f.__qualname__}", "cpu_s": spent - nested, "end": time.monotonic()}
            )

    ev.register("numba:compile", Compiles())
    atexit.register(lambda: Path(records).write_text(json.dumps(compiles)))
    from hmdrt.cli import main

    return main(argv)


def first_start(config: str, duration_s: float) -> dict:
    """One run of `config` from an empty numba cache: seconds to the first VSync, the start-up's steps (the
    "started:" line's, and the time before them), and the kernels compiled."""
    with tempfile.TemporaryDirectory(prefix="hmdrt-first-start-") as folder:
        records = Path(folder, "compiles.json")
        command = [sys.executable, __file__, "--child", str(records), "run", config, "--duration", str(duration_s)]
        command += ["--report", str(Path(folder, "report.json"))]
        env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(folder, "numba"))}
        load = os.getloadavg()[0]
        began = time.monotonic()
        proc = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, text=True)
        started, line = None, ""
        for line in proc.stdout:
            if "started: " in line:
                started = time.monotonic()
                break
        proc.stdout.read()
        if proc.wait(timeout=duration_s + 120) != 0 or started is None:
            raise SystemExit(f"hmdrt run {config} failed (exit {proc.returncode}): {line.strip()!r}")
        compiles = json.loads(records.read_text())
    steps = {}
    for part in line.split("started: ", 1)[1].split(";", 1)[0].split(", "):
        found = STEP.fullmatch(part.strip())
        if found:
            steps[found[1]] = float(found[2])
    before = started - began - sum(steps.values())
    kernels: dict[str, list[float]] = defaultdict(list)
    for record in compiles:
        kernels[record["kernel"]].append(record["cpu_s"])
    return {
        "load_average": load,
        "first_vsync_s": started - began + FIRST_PRESENT_S,
        "steps_s": {"before the steps (interpreter, imports, scene and tracer set-up)": before, **steps},
        "compiles": len(compiles),
        "compile_cpu_s": sum(r["cpu_s"] for r in compiles),
        "after_first_vsync": sorted({r["kernel"] for r in compiles if r["end"] > started}),
        "kernels": sorted(([k, sum(s), len(s)] for k, s in kernels.items()), key=lambda k: -k[1]),
    }


def show(run: dict, top: int) -> None:
    print(f"  first VSync {run['first_vsync_s']:.1f} s after the command (load average {run['load_average']:.1f})")
    for what, seconds in run["steps_s"].items():
        print(f"    {seconds:5.1f} s  {what}")
    late = ", ".join(run["after_first_vsync"]) or "none"
    print(f"  {run['compiles']} compiles, {run['compile_cpu_s']:.1f} s of CPU; after the first VSync: {late}")
    print(f"  the {top} longest, CPU seconds without the kernels each compiled on the way (xN: N signatures):")
    for kernel, seconds, signatures in run["kernels"][:top]:
        print(f"    {seconds:5.2f}  {kernel}" + (f" x{signatures}" if signatures > 1 else ""))


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--child":
        raise SystemExit(child(sys.argv[2], sys.argv[3:]))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="configs/default.toml")
    ap.add_argument("--duration", type=float, default=2.0, help="seconds the compositor runs after its start")
    ap.add_argument("--top", type=int, default=12, help="kernels listed")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--json", help="write the runs' figures here")
    args = ap.parse_args()
    from hmdrt.evaluate.provenance import stamp

    where = stamp()
    print(f"hmdrt run {args.config}, numba's cache empty: {where['date']}, {where['commit']}, {where['machine']}")
    runs = []
    for k in range(args.repeats):
        runs.append(first_start(args.config, args.duration))
        print(f"run {k + 1}:")
        show(runs[-1], args.top)
    if args.repeats > 1:
        print(f"median first VSync {statistics.median(r['first_vsync_s'] for r in runs):.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps({**where, "config": args.config, "runs": runs}, indent=1))


if __name__ == "__main__":
    main()
