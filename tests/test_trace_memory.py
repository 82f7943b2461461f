"""The memory of reading traces: `hmdrt convert` and replay:// hold a trace's samples as numpy columns (106 bytes a
sample, replay/table.py) and read and write it a chunk at a time, so their peak memory is the table and a fixed
amount, however the file compresses; an inflated size past the cap, and a sample count past the cap, are one line.

Peak memory is measured as it is: the peak resident set (VmHWM) of a real subprocess doing the work.
Traces that inflate a lot are gzip files of many members, each the same compressed block of valid samples (gzip
readers read every member): cheap to make, as a file that inflates 100-fold is.
"""

from __future__ import annotations

import gzip
import re
import subprocess
import sys
from pathlib import Path

import msgspec
import pytest

from hmdrt.bus.messages import Gaze, Pose
from hmdrt.cli import main
from hmdrt.errors import ConfigError
from hmdrt.replay import load_trace, table, trace
from hmdrt.replay.table import BLOCK, BYTES_PER_SAMPLE, SampleTable

HEADER = b'{"format":"hmdrt-trace","v":1,"device":"eye"}\n'
BLOCK_SAMPLES = 16_384  # samples in each gzip member
MIB = 1024 * 1024
FIXED_MIB = 32  # what reading and writing may take besides the table: a few chunks, whatever the file's size
PLAYER_BYTES = 16 + 24  # replay's order and sorted times a sample, and its sort's transient columns
PEAK = 'print("peak", next(line.split()[1] for line in open("/proc/self/status") if line.startswith("VmHWM:")), "kB")'
CONVERT = f"""import sys
from hmdrt.cli import main
status = main(["convert", *sys.argv[1:]])
{PEAK}
sys.exit(status)
"""
REPLAY = f"""import sys
from hmdrt.drivers import open_driver
driver = open_driver(f"replay://{{sys.argv[1]}}?speed=0")
driver.open()
while driver.state != "ended":
    driver.read(0.0)
print(driver.counters.samples, "samples replayed")
{PEAK}
"""


def binocular(k: int) -> Gaze:
    """A binocular sample of a recording at 250 Hz, its gaze still (so that a block of them compresses 37-fold)."""
    return Gaze(
        seq=k,
        t_host=k * 4_000_000,
        t_dev=k * 4_000_000 + 500_000,
        C=(0.0005133580271952893, 0.00004960616915535703, -0.999999867001373),
        L=(0.011191490583765472, 0.00004960306902119937, -0.9999373720778962),
        R=(-0.010164950130422918, 0.00004960361281657873, -0.999948334329493),
        depth_m=2.973171594528768,
    )


def inflating_trace(path: Path, members: int) -> tuple[int, int]:
    """A native gzip trace of `members` copies of one compressed block of binocular samples; (samples, inflated
    bytes)."""
    block = msgspec.json.Encoder().encode_lines([binocular(k) for k in range(BLOCK_SAMPLES)])
    member = gzip.compress(block, 9, mtime=0)
    with path.open("wb") as f:
        f.write(gzip.compress(HEADER, mtime=0))
        for _ in range(members):
            f.write(member)
    return BLOCK_SAMPLES * members, len(HEADER) + len(block) * members


def peak_rss_mib(code: str, *args: str) -> tuple[float, int, str]:
    """Run `python -c code args` to its end: its peak resident memory in MiB (the VmHWM the code prints last: the
    peak of its own address space, without the parent's that rusage counts for the moment before exec), its exit
    status and its output."""
    process = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True)
    output = process.stdout + process.stderr
    peak = re.search(r"^peak (\d+) kB$", process.stdout, re.MULTILINE)
    assert peak, output
    return int(peak.group(1)) / 1024, process.returncode, output


def run(kind: str, source: Path, folder: Path) -> tuple[float, str]:
    """The peak memory and output of converting `source` to native JSONL in `folder`, or of replaying it."""
    if kind == "convert":
        peak, status, out = peak_rss_mib(CONVERT, str(source), str(folder / f"{source.name}.out.jsonl"), "--force")
    else:
        peak, status, out = peak_rss_mib(REPLAY, str(source))
    assert status == 0, out
    return peak, out


@pytest.fixture(scope="module")
def baseline(tmp_path_factory) -> dict[str, float]:
    """Per kind, the peak memory of the same work on a trace of one block (the interpreter, numpy, hmdrt), its
    second run's (the first may compile the modules' bytecode)."""
    folder = tmp_path_factory.mktemp("baseline")
    small = folder / "one.jsonl.gz"
    inflating_trace(small, 1)
    return {kind: [run(kind, small, folder)[0] for _ in range(2)][-1] for kind in ("convert", "replay")}


@pytest.mark.parametrize("kind", ["convert", "replay"])
def test_memory_is_the_table_and_a_fixed_amount_not_the_file(tmp_path, baseline, kind):
    """A 1 MB gzip inflating to 45 MB: peak memory past the baseline stays within the table's 106 bytes a sample
    (replay: 40 more) and FIXED_MIB. Per-sample objects took about 600 bytes a sample, and the output was built
    whole in memory, far past this."""
    source = tmp_path / "inflates.jsonl.gz"
    samples, inflated = inflating_trace(source, 9)
    assert inflated > 40e6 and source.stat().st_size < inflated / 30
    peak, out = run(kind, source, tmp_path)
    assert f"{samples} samples" in out
    per_sample = BYTES_PER_SAMPLE + (PLAYER_BYTES if kind == "replay" else 0)
    allowed = samples * per_sample / MIB + FIXED_MIB
    assert peak - baseline[kind] < allowed, f"{kind}: {peak - baseline[kind]:.0f} MB past the baseline"


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["convert", "replay"])
def test_a_gzip_inflating_to_400_mb_converts_and_replays_under_600_mb(tmp_path, kind):
    """Issue 42: a gzip of valid samples inflating to 400 MB took 1.64 GB to convert and replay."""
    source = tmp_path / "inflates.jsonl.gz"
    samples, inflated = inflating_trace(source, 81)
    assert inflated > 400e6
    peak, out = run(kind, source, tmp_path)
    assert f"{samples} samples" in out and peak < 600, f"{kind}: peak {peak:.0f} MB"


def gzip_bomb(path: Path, inflated: int) -> None:
    """A gzip file of `inflated` bytes with no line break (members of 64 MiB of one byte)."""
    member = gzip.compress(b"x" * (64 * MIB), 9, mtime=0)
    with path.open("wb") as f:
        for _ in range(-(-inflated // (64 * MIB))):
            f.write(member)


def test_an_inflated_size_past_the_cap_is_one_line_naming_it(tmp_path, capsys, monkeypatch):
    """With the cap lowered, a trace inflating past it is refused by `hmdrt convert` in one line naming the cap, and
    nothing is written."""
    monkeypatch.setattr(trace, "MAX_FILE_BYTES", 2_000_000)
    source, out = tmp_path / "big.jsonl.gz", tmp_path / "out.jsonl"
    samples, inflated = inflating_trace(source, 1)
    assert inflated > 2_000_000 > source.stat().st_size
    assert main(["convert", str(source), str(out)]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [
        f"hmdrt: error: trace {source} holds more than 2000000 bytes (once inflated), the most hmdrt reads of a trace"
    ]
    assert not out.exists() and not list(tmp_path.glob(".out.jsonl*"))


@pytest.mark.slow
def test_a_gzip_bomb_past_the_real_cap_is_refused_in_bounded_memory(tmp_path, baseline):
    """2 MB of gzip inflating past the 2 GiB cap: one line naming the cap, read a chunk at a time (no memory in
    proportion to what it inflated to)."""
    bomb = tmp_path / "bomb.jsonl.gz"
    gzip_bomb(bomb, trace.MAX_FILE_BYTES + 64 * MIB)
    assert bomb.stat().st_size < 8e6
    peak, status, out = peak_rss_mib(CONVERT, str(bomb), str(tmp_path / "out.jsonl"))
    assert status == 1 and [line for line in out.splitlines() if not line.startswith("peak ")] == [
        f"hmdrt: error: trace {bomb} holds more than {trace.MAX_FILE_BYTES} bytes (once inflated), the most hmdrt "
        "reads of a trace"
    ]
    assert peak - baseline["convert"] < FIXED_MIB


@pytest.mark.parametrize(
    "name, text",
    [
        ("many.jsonl", HEADER.decode() + "".join(f'{{"kind":"gaze","seq":{k},"t_host":{k}}}\n' for k in range(30))),
        ("many.csv", "t_ms,yaw_deg,pitch_deg\n" + "".join(f"{k},1.0,2.0\n" for k in range(30))),
        ("many.asc", "START 1 LEFT SAMPLES\n" + "".join(f"{k} 960 540 1000 ...\n" for k in range(30))),
    ],
)
def test_a_sample_count_past_the_cap_is_one_line_naming_it(tmp_path, capsys, monkeypatch, name, text):
    """Every reader stops at the table's cap on samples with one line naming the trace and the cap."""
    monkeypatch.setattr(table, "MAX_SAMPLES", 20)
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError, match=f"^trace {path} holds more than 20 samples, the most hmdrt keeps"):
        load_trace(path)
    assert main(["convert", str(path), str(tmp_path / "out.jsonl")]) == 1
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_a_table_gives_back_exactly_the_samples_it_was_given(tmp_path):
    """Across block boundaries, with every optional field absent or present, the extremes of seq and time, and
    poses between gazes; a native trace reads into a table equal to its samples, and a seq past 64 bits is a
    malformed line."""
    samples = []
    for k in range(BLOCK + 5000):
        if k % 7 == 0:
            samples.append(Pose(k, -(2**62) + k, (0.0, 1.6, -0.0), (1.0, 0.0, 0.0, 0.0), None, k % 2 == 0))
        elif k % 7 == 1:
            samples.append(Gaze(2**64 - 1 - k, 2**62 - k, valid=False))
        else:
            samples.append(binocular(k) if k % 3 else Gaze(k, k, L=(0.0, 0.0, -1.0), depth_m=1e6))
    got = SampleTable.of(samples)
    assert got == samples and got[BLOCK] == samples[BLOCK] and got[-1] == samples[-1]
    assert got[BLOCK - 2 : BLOCK + 2] == samples[BLOCK - 2 : BLOCK + 2]
    assert got.nbytes == 2 * BLOCK * BYTES_PER_SAMPLE and BYTES_PER_SAMPLE == 106
    path = tmp_path / "t.jsonl.gz"
    trace.write_trace(path, samples[:100], device="eye")
    with gzip.open(path, "ab") as f:
        f.write(b'{"kind":"gaze","seq":18446744073709551616,"t_host":0}\n')
    reading = load_trace(path)
    assert reading.samples == samples[:100] and reading.malformed == 1
