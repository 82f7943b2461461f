"""Seconds from `hmdrt run` to its first VSync on a fresh install, each start-up step's time, and the kernels that
took longest to compile.

    python bench/first_start.py [--config configs/default.toml] [--top 12] [--repeats 1] [--json PATH]

Runs the compositor for 2 s in a subprocess whose numba cache is a new, empty folder (NUMBA_CACHE_DIR: an editable
install otherwise caches beside the sources, in __pycache__, and a second run would load it), as a first run does.
The first VSync is timed from the command to the "started:" line, which the compositor prints as its VSync clock
starts (the first VSync 50 ms later, daemon.FIRST_PRESENT_NS). numba's compile events, in the compositor and in any
process it starts (the second process that compiles the tracer on a first run: hmdrt.trace.compile_aside), give
each kernel's CPU seconds, not counting the kernels it compiled on the way, and which kernels the compositor
compiled after the first VSync (none should be: a compile there stalls the frame it happens in). These machines are
shared: the load average at the start is printed, and CPU seconds vary less with it than the wall time does.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

ROOT = Path(__file__).resolve().parent.parent
FIRST_PRESENT_S = 0.05  # hmdrt.compositor.daemon.FIRST_PRESENT_NS: the first VSync after the "started:" line
STEP = re.compile(r"(.+) (\d+(?:\.\d+)?) s")


# Put on the run's PYTHONPATH as sitecustomize, so that every Python process of the run (the compositor and the second
# process that compiles the tracer, hmdrt.trace.compile_aside) records numba's compile events: each kernel compiled
# (module.name), its CPU seconds less those of the kernels it compiled on the way, and when it ended
# (time.monotonic), written as JSON into the folder $HMDRT_COMPILES when the process exits.
RECORDER = """
import atexit, json, os, sys, threading, time
from pathlib import Path

import numba.core.event as ev

compiles = []
frames = threading.local()  # per thread: [CPU time at start, CPU seconds of nested compiles] of open compiles


class Compiles(ev.Listener):
    def on_start(self, event):
        if not hasattr(frames, "open"):
            frames.open = []
        frames.open.append([time.thread_time(), 0.0])

    def on_end(self, event):
        began, nested = frames.open.pop()
        spent = time.thread_time() - began
        if frames.open:
            frames.open[-1][1] += spent
        f = event.data["dispatcher"].py_func
        kernel = f"{f.__module__}.{f.__qualname__}"
        compiles.append({"kernel": kernel, "cpu_s": spent - nested, "end": time.monotonic()})


ev.register("numba:compile", Compiles())
record = Path(os.environ["HMDRT_COMPILES"], f"{os.getpid()}.json")
atexit.register(lambda: record.write_text(json.dumps({"argv": sys.argv, "compiles": compiles})))
"""


def first_start(config: str, duration_s: float) -> dict:
    """One run of `config` from an empty numba cache: seconds to the first VSync, the start-up's steps (the
    "started:" line's, and the time before them), and the kernels compiled."""
    with tempfile.TemporaryDirectory(prefix="hmdrt-first-start-") as folder:
        site, records = Path(folder, "site"), Path(folder, "compiles")
        site.mkdir()
        records.mkdir()
        (site / "sitecustomize.py").write_text(RECORDER)
        command = [sys.executable, "-m", "hmdrt", "run", config, "--duration", str(duration_s)]
        command += ["--report", str(Path(folder, "report.json"))]
        paths = os.pathsep.join(p for p in (str(site), os.environ.get("PYTHONPATH")) if p)
        env = {**os.environ, "NUMBA_CACHE_DIR": str(Path(folder, "numba")), "PYTHONPATH": paths}
        env["HMDRT_COMPILES"] = str(records)
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
        processes = {int(f.stem): json.loads(f.read_text()) for f in records.glob("*.json")}
    compiles = processes.pop(proc.pid)["compiles"]  # the compositor's; the rest are processes it started
    aside = [record for p in processes.values() for record in p["compiles"]]
    steps = {}
    for part in line.split("started: ", 1)[1].split(";", 1)[0].split(", "):
        found = STEP.fullmatch(part.strip())
        if found:
            steps[found[1]] = float(found[2])
    before = started - began - sum(steps.values())
    kernels: dict[str, list[float]] = defaultdict(list)
    for record in compiles:
        kernels[record["kernel"]].append(record["cpu_s"])
    for record in aside:
        kernels[record["kernel"] + " (second process)"].append(record["cpu_s"])
    return {
        "load_average": load,
        "first_vsync_s": started - began + FIRST_PRESENT_S,
        "steps_s": {"before the steps (interpreter, imports, scene and tracer set-up)": before, **steps},
        "compiles": len(compiles),
        "compile_cpu_s": sum(r["cpu_s"] for r in compiles),
        "aside_compiles": len(aside),
        "aside_cpu_s": sum(r["cpu_s"] for r in aside),
        "after_first_vsync": sorted({r["kernel"] for r in compiles if r["end"] > started}),
        "kernels": sorted(([k, sum(s), len(s)] for k, s in kernels.items()), key=lambda k: -k[1]),
    }


def show(run: dict, top: int) -> None:
    print(f"  first VSync {run['first_vsync_s']:.1f} s after the command (load average {run['load_average']:.1f})")
    for what, seconds in run["steps_s"].items():
        print(f"    {seconds:5.1f} s  {what}")
    late = ", ".join(run["after_first_vsync"]) or "none"
    print(
        f"  {run['compiles']} compiles in the compositor, {run['compile_cpu_s']:.1f} s of CPU; "
        f"{run['aside_compiles']} in a second process, {run['aside_cpu_s']:.1f} s; "
        f"in the compositor after the first VSync: {late}"
    )
    print(f"  the {top} longest, CPU seconds without the kernels each compiled on the way (xN: N signatures):")
    for kernel, seconds, signatures in run["kernels"][:top]:
        print(f"    {seconds:5.2f}  {kernel}" + (f" x{signatures}" if signatures > 1 else ""))


def main() -> None:
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
