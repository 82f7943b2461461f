"""bench/perf_profile.py: its map names numba's code where it lies in this process, and perf, where it can sample
here, attributes a method's frames to those names."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys

import numpy as np
import pytest

from hmdrt.foveation.stages import pyramid, temporal
from tests.test_registry import BENCH, bench_module


@pytest.fixture(scope="module")
def perf_profile():
    return bench_module("perf_profile")


def _entry(dispatcher) -> int:
    """The address of a compiled function's code, as numba's engine gives it."""
    result = next(iter(dispatcher.overloads.values()))
    return result.library.get_pointer_to_function(result.fndesc.llvm_func_name)


def _named_at(symbols, address: int) -> str:
    (name,) = [s.name for s in symbols if s.address <= address < s.address + s.size]
    return name


def test_the_map_names_a_serial_kernel_where_its_code_lies(perf_profile):
    temporal.age_table(0.1, 0.5, 8.0, np.empty(4))  # compiled, or loaded from numba's cache
    symbols = perf_profile.code_symbols()
    assert _named_at(symbols, _entry(temporal.age_table)) == "hmdrt.foveation.stages.temporal.age_table"
    addresses = [s.address for s in symbols]
    assert addresses == sorted(addresses) and all(s.size > 0 for s in symbols)


def test_the_map_names_a_parallel_kernels_body_after_its_kernel(perf_profile):
    pyr = pyramid.Pyramid.empty(8, 6)
    pyr.data[:, pyramid.WEIGHT] = 1.0
    pyramid.pull_push(pyr, None)
    names = {s.name for s in perf_profile.code_symbols()}
    assert "hmdrt.foveation.stages.pyramid._pull_level (parallel body)" in names


def test_a_map_line_is_start_size_and_name_in_hex(perf_profile, tmp_path, monkeypatch):
    monkeypatch.setattr(perf_profile.tempfile, "gettempdir", lambda: str(tmp_path))
    symbol = perf_profile.CodeSymbol(0x7F00_0000_1000, 0x2A0, "hmdrt.trace.surface.surface_block")
    path = perf_profile.write_perf_map([symbol], pid=4321)
    assert path == tmp_path / "perf-4321.map"
    assert path.read_text() == "7f0000001000 2a0 hmdrt.trace.surface.surface_block\n"


def test_numba_symbols_read_as_dotted_names(perf_profile):
    mangled = "_ZN5hmdrt5trace7surface13surface_blockB3v92B40c8tJTIeFIjxB2IKSgI4CrvQClQZ6FcpCShpgEU0AE386Geometry"
    assert perf_profile.symbol_name(mangled) == "hmdrt.trace.surface.surface_block"
    assert perf_profile.symbol_name("NRT_incref") == "NRT_incref"


@pytest.mark.skipif(shutil.which("objdump") is None, reason="objdump (binutils) is not installed")
def test_hot_instructions_are_counted_in_objdumps_listing_of_the_code(perf_profile):
    code = bytes([0x48, 0x01, 0xD8, 0x90, 0xC3])  # add %rbx,%rax; nop; ret
    listing = perf_profile.disassemble(code, 0x1000)
    assert [(a, text.split()[0]) for a, text in listing.items()] == [(0x1000, "add"), (0x1003, "nop"), (0x1004, "ret")]
    symbol = perf_profile.CodeSymbol(0x1000, len(code), "f")
    lines = perf_profile.hot_instructions([0x1003, 0x1003, 0x1000, 0x9999], symbol, listing, 5)
    assert "3 of 4 samples" in lines[0]
    assert lines[1].split()[:3] == ["66.67", "0x3:", "nop"] and lines[2].split()[:3] == ["33.33", "0x0:", "add"]


def _perf_samples_here() -> bool:
    perf = shutil.which("perf")
    if perf is None:
        return False
    probe = [perf, "record", "-q", "-o", "/dev/null", "--", sys.executable, "-c", "pass"]
    return subprocess.run(probe, capture_output=True).returncode == 0


@pytest.mark.skipif(not _perf_samples_here(), reason="perf is not installed or may not sample here")
def test_a_methods_frames_are_attributed_to_its_kernels_by_name():
    run = [sys.executable, str(BENCH / "perf_profile.py"), "rrm", "--profile", "sim-cpu", "--seconds", "2"]
    annotate = shutil.which("objdump") is not None
    run += ["--annotate", "hmdrt.trace.surface.surface_block"] if annotate else []
    done = subprocess.run(run, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    assert "numba's code" in lines[1]
    table = lines[3:]
    if annotate:  # the surface records' instructions follow the table, each with its share of their samples
        at = next(i for i, line in enumerate(lines) if line.startswith("  hmdrt.trace.surface.surface_block: "))
        table, hot = lines[3:at], lines[at + 1 :]
        assert hot and all(re.match(r"\s+[\d.]+\s+0x[0-9a-f]+: \w+", line) for line in hot), done.stdout
    functions = [line.split(maxsplit=1)[1] for line in table]
    assert any(f.startswith("hmdrt.foveation.rrm.") for f in functions), done.stdout  # rrm's own kernels, by name
    assert any(f.startswith("hmdrt.trace.") for f in functions), done.stdout
