"""Where a method's frames spend the CPU, function by function, numba's compiled code included: Linux perf, sampling.

    python bench/perf_profile.py SPEC [--scene whitted] [--profile rift_s] [--frames 30] [--warmup 3]
                                      [--trace builtin] [--gaze 0,0] [--seconds 5] [--frequency 999] [--top 25]
                                      [--annotate FUNCTION]

perf sees numba's code as anonymous memory ("[JIT]"), with no names. So after --warmup frames (compiles, an empty
history) this bench writes /tmp/perf-PID.map, where perf looks for the names of such code: every function numba
compiled or loaded from its cache for hmdrt's modules, by its address in this process (sizes up to the next
function's address, as numba keeps no symbol sizes), a parallel kernel's body under its kernel's name. Then it has
`perf record` sample this process for --seconds while it renders the method's frames (the --frames requests over
and over), and prints the share of samples by library (numba's code, embreex's Embree, libgomp: numba's OpenMP
threads, Python) and the --top functions. A function's share is of both cores' samples: a function at 10% of a
2-core frame of 80 ms takes about 16 ms of CPU a frame. Functions LLVM inlined are counted in their callers.
--annotate FUNCTION (a name as the list prints it) adds that function's hottest machine instructions, its code read
from this process and disassembled with objdump: a sample lands on the instruction after the one that stalls (a
load that missed the cache, a division), so read each hot line with the one above it.

perf must be installed (linux-tools; `perf_event_paranoid` at 2 or below lets a user sample its own processes).
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numba
import numpy as np
from references import frame_arguments, left_eye_requests

from hmdrt.evaluate.provenance import stamp
from hmdrt.foveation import make_method
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

MOST_BYTES = 1 << 20  # a function's size in the map at most (its end is unknown: the next function's start)


class CodeSymbol(NamedTuple):
    address: int
    size: int
    name: str


def symbol_name(symbol: str) -> str:
    """A numba symbol as the dotted name of its Python function (`_ZN5hmdrt5trace7surface13surface_blockB3v92...`:
    hmdrt.trace.surface.surface_block); the symbol itself where it is no such name."""
    if not symbol.startswith("_ZN"):
        return symbol
    parts, i = [], 3
    while i < len(symbol) and symbol[i].isdigit():
        digits = re.match(r"\d+", symbol[i:]).group()
        start = i + len(digits)
        parts.append(symbol[start : start + int(digits)])
        i = start + int(digits)
    return ".".join(parts) if parts else symbol


def _libraries(library, seen: dict[int, object]) -> None:
    """A numba code library and those linked into it (a parallel kernel's body), each once."""
    if id(library) not in seen:
        seen[id(library)] = library
        for linked in getattr(library, "_linking_libraries", ()):
            _libraries(linked, seen)


def _dispatchers(prefix: str) -> Iterator[tuple[str, numba.core.dispatcher.Dispatcher]]:
    """numba's functions in the modules named `prefix`..., each with its dotted name."""
    for module in list(sys.modules.values()):
        if getattr(module, "__name__", "").startswith(prefix):
            for value in list(vars(module).values()):
                if isinstance(value, numba.core.dispatcher.Dispatcher):
                    yield f"{value.py_func.__module__}.{value.py_func.__qualname__}", value


def code_symbols(prefix: str = "hmdrt") -> list[CodeSymbol]:
    """The functions of numba's code loaded for the modules named `prefix`...: each one's address and name (a
    parallel kernel's body as its kernel's, marked), in address order."""
    names: dict[int, str] = {}
    for kernel, dispatcher in _dispatchers(prefix):
        seen: dict[int, object] = {}
        for result in dispatcher.overloads.values():
            _libraries(result.library, seen)
        for library in seen.values():
            engine = library._codegen._engine
            modules = [m for m in (library._shared_module, library._final_module) if m is not None]
            for function in {f.name for m in modules for f in m.functions}:
                address = engine.get_function_address(function)
                if address:
                    name = symbol_name(function)
                    names[address] = f"{kernel} (parallel body)" if "parfor" in function else name
    ordered = sorted(names.items())
    ends = [a for a, _ in ordered[1:]] + [ordered[-1][0] + MOST_BYTES] if ordered else []
    return [CodeSymbol(a, min(end - a, MOST_BYTES), n) for (a, n), end in zip(ordered, ends, strict=True)]


def write_perf_map(symbols: list[CodeSymbol], pid: int | None = None) -> Path:
    """perf's map of this process's JIT code, /tmp/perf-PID.map: one `START SIZE NAME` line (hex) per function."""
    path = Path(tempfile.gettempdir()) / f"perf-{os.getpid() if pid is None else pid}.map"
    path.write_text("".join(f"{s.address:x} {s.size:x} {s.name}\n" for s in symbols))
    return path


REPORT_LINE = re.compile(r"\s*([\d.]+)%\s+(\S.*?)\s+\[[.k]\]\s+(.+?)\s*$")


def parse_report(text: str) -> list[tuple[float, str, str]]:
    """`perf report --sort dso,sym` lines as (percent, library, function), most first; the addresses of a library
    without symbols (Embree's) summed into one row, "unnamed code"."""
    rows: dict[tuple[str, str], float] = {}
    for line in text.splitlines():
        found = REPORT_LINE.match(line)
        if found:
            dso, function = found[2].strip(), found[3]
            key = (dso, "unnamed code" if function.startswith("0x") else function)
            rows[key] = rows.get(key, 0.0) + float(found[1])
    return sorted(((p, dso, f) for (dso, f), p in rows.items()), key=lambda row: -row[0])


def code_bytes(symbol: CodeSymbol) -> bytes:
    """The machine code of a function of this process (as far as it is mapped: its size is a bound)."""
    code = b""
    with open("/proc/self/mem", "rb", buffering=0) as memory:
        for page in range(0, symbol.size, 4096):
            try:
                memory.seek(symbol.address + page)
                code += memory.read(min(4096, symbol.size - page))
            except OSError:
                break
    return code


def disassemble(code: bytes, address: int) -> dict[int, str]:
    """objdump's x86-64 disassembly of `code` placed at `address`: each instruction's address and text."""
    with tempfile.NamedTemporaryFile(suffix=".bin") as raw:
        raw.write(code)
        raw.flush()
        command = ["objdump", "-D", "-b", "binary", "-m", "i386:x86-64", f"--adjust-vma={address:#x}", raw.name]
        text = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    found = (re.match(r"\s*([0-9a-f]+):\s+(?:[0-9a-f]{2} )+\s*(\S.*)", line) for line in text.splitlines())
    return {int(m[1], 16): m[2].strip() for m in found if m}


def hot_instructions(ips: list[int], symbol: CodeSymbol, listing: dict[int, str], top: int) -> list[str]:
    """The `top` instructions of `listing` with the most of the sampled instruction pointers `ips`, as lines."""
    inside = [ip for ip in ips if symbol.address <= ip < symbol.address + symbol.size]
    lines = [f"  {symbol.name}: {len(inside)} of {len(ips)} samples; its hottest instructions, % of its samples:"]
    for ip, n in Counter(inside).most_common(top):
        lines.append(f"  {100 * n / len(inside):12.2f}  {ip - symbol.address:#7x}: {listing.get(ip, '?')}")
    return lines


def library_of(dso: str) -> str:
    """The kind of library a perf dso is: numba's code, embree, libgomp, Python, the kernel, or itself."""
    if dso.startswith("[JIT]"):
        return "numba's code"
    for key, kind in (("embree", "Embree"), ("libgomp", "libgomp (numba's OpenMP threads)"), ("python", "Python")):
        if key in dso:
            return kind
    return "the kernel" if dso.startswith("[kernel") else dso


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spec", help="the method, as the other benches take it (weier18?dof=none)")
    frame_arguments(ap, 30, 3)
    ap.add_argument("--seconds", type=float, default=5.0)
    ap.add_argument("--frequency", type=int, default=999, help="samples per second per CPU")
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument("--annotate", metavar="FUNCTION", help="also the hottest instructions of this function")
    args = ap.parse_args()
    perf = shutil.which("perf")
    if perf is None:
        sys.exit("perf is not installed (a Linux distribution's linux-tools or linux-perf package)")
    if args.annotate and shutil.which("objdump") is None:
        sys.exit("--annotate needs objdump (binutils)")

    scene, profile = load_scene(args.scene), get_profile(args.profile)
    requests = left_eye_requests(scene, profile, max(args.frames, args.warmup + 1), args.trace, args.gaze)
    with Whitted(scene, None) as tracer, tempfile.TemporaryDirectory() as tmp:
        method = make_method(args.spec, tracer)
        out = np.empty((profile.height, profile.width, 3), np.float32)
        for request in requests[: args.warmup]:
            method.render(request, FrameStats(), out)
        symbols = code_symbols()
        perf_map = write_perf_map(symbols)
        annotated = [s for s in symbols if s.name == args.annotate]
        if args.annotate and not annotated:
            sys.exit(f"--annotate {args.annotate}: no such function of numba's code in this process")
        code = [(s, code_bytes(s)) for s in annotated]
        data = Path(tmp) / "perf.data"
        record = [perf, "record", "-q", "-F", str(args.frequency), "-p", str(os.getpid()), "-o", str(data)]
        sampler = subprocess.Popen([*record, "--", "sleep", str(args.seconds)], stderr=subprocess.PIPE, text=True)
        frames = 0
        while sampler.poll() is None:
            method.render(requests[args.warmup + frames % (len(requests) - args.warmup)], FrameStats(), out)
            frames += 1
        if sampler.returncode != 0:
            sys.exit(f"perf record failed: {sampler.stderr.read().strip()}")
        report = subprocess.run(
            [perf, "report", "-i", str(data), "--no-children", "--sort", "dso,sym", "-g", "none", "--stdio"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        annotation = []
        if code:
            script = [perf, "script", "-i", str(data), "-F", "ip"]
            ips = [int(ip, 16) for ip in subprocess.run(script, capture_output=True, text=True).stdout.split()]
            symbol, raw = max(code, key=lambda sc: sum(sc[0].address <= ip < sc[0].address + sc[0].size for ip in ips))
            annotation = hot_instructions(ips, symbol, disassemble(raw, symbol.address), args.top)
        perf_map.unlink(missing_ok=True)

    rows = parse_report(report)
    where = stamp()
    view = "built-in head path" if args.trace else "still view"
    print(
        f"{args.spec} on {args.scene} at {args.profile}, {view}: {frames} frames in {args.seconds:g} s of perf "
        f"sampling, after {args.warmup}: {where['date']}, {where['commit']}, {where['machine']}"
    )
    by_library: dict[str, float] = {}
    for percent, dso, _ in rows:
        by_library[library_of(dso)] = by_library.get(library_of(dso), 0.0) + percent
    shares = sorted(((v, k) for k, v in by_library.items() if v >= 0.1), reverse=True)
    print("  by library: " + ", ".join(f"{k} {v:.1f}%" for v, k in shares))
    print(f"  {'% of samples':>12s}  function")
    for percent, dso, function in rows[: args.top]:
        print(f"  {percent:12.2f}  {function if dso.startswith('[JIT]') else f'{function} ({dso})'}")
    for line in annotation:
        print(line)


if __name__ == "__main__":
    main()
