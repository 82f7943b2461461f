"""A disk that fills up, and frees again, under hmdrt's writers: the frames log goes on with whole lines, its readers
skip and count a line an older writer tore, a run's report and summary line outlive a full disk, and a snapshot
that cannot be written leaves no file.

The disk is a small tmpfs mounted for the test (root only; skipped where mount fails), filled with a file that
takes every free page and freed by removing it.
"""

from __future__ import annotations

import errno
import json
import logging
import os
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from PIL import Image

from hmdrt.cli import main
from hmdrt.compositor.endpoints import request
from hmdrt.telemetry.frames_log import FramesHeader, FramesLog, read_frames_log
from hmdrt.telemetry.report import FrameRecord
from hmdrt.testing import ANY_PORT, compositor, run_bounded, write_config

SIZE = "1m"
PAGE = os.sysconf("SC_PAGE_SIZE")
NO_SPACE = os.strerror(errno.ENOSPC)
HEADER = FramesHeader(vsync_hz=30.0, period_ns=33_333_333)
STAGES = {f"stage_{i}": float(i) for i in range(400)}  # a line longer than a page: one that cannot fit in a page's rest


class Disk:
    """A mounted tmpfs that fill() leaves without a free page and free() empties again."""

    def __init__(self, root: Path):
        self.root = root
        self.filler = root / "filler"

    def fill(self) -> None:
        with self.filler.open("ab", buffering=0) as f:
            chunk = 1 << 16
            while chunk:
                try:
                    f.write(bytes(chunk))
                except OSError as exc:
                    assert exc.errno == errno.ENOSPC, exc
                    chunk //= 2

    def free(self) -> None:
        self.filler.unlink()


@pytest.fixture
def disk(tmp_path: Path) -> Iterator[Disk]:
    if os.geteuid() != 0:
        pytest.skip("a small disk to fill is a tmpfs mounted for the test, which needs root")
    root = tmp_path / "disk"
    root.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={SIZE}", "hmdrt-test", str(root)], capture_output=True
    )
    if mounted.returncode:
        pytest.skip(f"cannot mount a tmpfs here: {mounted.stderr.decode().strip()}")
    try:
        yield Disk(root)
    finally:
        subprocess.run(["umount", "--lazy", str(root)], check=True)


def record(vsync: int) -> dict:
    return FrameRecord(vsync, vsync, "new", 0, 0, 0, 0, 0, 0, 0, False, None, None, stages_ms=STAGES).to_dict()


def wait_for(holds, what: str, timeout_s: float = 10.0) -> None:
    end = time.monotonic() + timeout_s
    while not holds():
        assert time.monotonic() < end, f"no {what} in {timeout_s} s"
        time.sleep(0.01)


def test_a_frames_log_written_across_a_full_disk_goes_on_with_whole_lines(disk, caplog):
    path = disk.root / "frames.jsonl"
    log = FramesLog(path, HEADER, block=True)
    log.start()
    try:
        for vsync in range(3):
            log.offer(record(vsync))
        wait_for(lambda: path.read_bytes().count(b"\n") == 4, "3 records written")
        kept = path.read_bytes()
        assert len(kept) % PAGE, "the log ends on a page boundary: the next line would not be torn"
        disk.fill()
        for vsync in range(3, 6):  # each fills the rest of the log's last page, then finds no room
            log.offer(record(vsync))
        wait_for(lambda: log.failed == 3, "3 records failed")
        assert path.read_bytes() == kept  # no part of a line left
        disk.free()
        for vsync in range(6, 9):
            log.offer(record(vsync))
    finally:
        log.close()
    reading = read_frames_log(path)
    assert [r.vsync for r in reading.records] == [0, 1, 2, 6, 7, 8] and not reading.corrupt and not reading.cut
    assert log.failed == 3 and log.lost == 3
    assert f"{path}: writing again; 3 records could not be written" in caplog.text


def test_lines_torn_mid_file_are_skipped_and_counted_by_the_plots_and_the_timeline(tmp_path, capsys):
    path = tmp_path / "frames.jsonl"
    log = FramesLog(path, HEADER)
    log.start()
    for vsync in range(8):
        log.offer(record(vsync))
    log.close()
    lines = path.read_bytes().splitlines(keepends=True)  # the header, then VSync n on line n + 2
    at_value = lines[6].index(b'"gaze":') + len(b'"gaze":')  # the next line read as this one's gaze: not JSON either
    torn = [lines[3][: len(lines[3]) // 2] + lines[4], b"\n", lines[6][:at_value] + lines[7]]  # cut, then the next
    path.write_bytes(b"".join([*lines[:3], torn[0], *lines[5:6], torn[1], torn[2], lines[8]]))
    assert main(["report", "plot", str(path), "--out", str(tmp_path / "plots")]) == 0
    assert main(["export", "perfetto", str(path), "--out", str(tmp_path / "trace.json")]) == 0
    err = capsys.readouterr().err.splitlines()
    warning = f"hmdrt: WARNING: hmdrt.telemetry.frames_log: {path}: 3 lines not JSON (torn by a full disk?) left out, "
    assert err == [warning + "the first at line 4"] * 2
    assert Image.open(tmp_path / "plots" / "timeline.png").format == "PNG"
    reading = read_frames_log(path)
    assert reading.corrupt == 3 and [r.vsync for r in reading.records] == [0, 1, 4, 7]


@pytest.mark.usefixtures("own_signals")
@pytest.mark.parametrize("runtime_folder", ["free", "full"])
def test_a_full_disk_at_the_end_of_a_run_keeps_the_summary_line_and_the_report(
    disk, tmp_path, runtime_dir, monkeypatch, capsys, runtime_folder
):
    config = write_config(tmp_path / "run.toml", eyes="left", bus={"control": ANY_PORT})
    report = disk.root / "report.json"
    if runtime_folder == "full":
        monkeypatch.setenv("XDG_RUNTIME_DIR", str(disk.root))
    disk.fill()
    assert main(["run", str(config), "--frames", "3", "--virtual-time", "--report", str(report)]) == 1
    out, err = capsys.readouterr()
    # (the tcp:// control socket's warning that every local user can reach it comes first)
    summary, errors = out.splitlines()[-1], [line for line in err.splitlines() if " WARNING: " not in line]
    failed = f"hmdrt: error: cannot write {report}: {NO_SPACE}; the run report is"
    if runtime_folder == "free":
        (fallback,) = (runtime_dir / "hmdrt").glob("report-*.json")
        assert errors == [f"{failed} in {fallback} instead"]
        assert json.loads(fallback.read_text())["vsyncs"] == 3
        assert summary.startswith("3 VSyncs: 3 frames shown") and summary.endswith(f"; report {fallback}")
    else:
        assert errors[0] == f"{failed} on the next line instead" and json.loads(errors[1])["vsyncs"] == 3
        assert summary.startswith("3 VSyncs: 3 frames shown") and summary.endswith("; report on stderr")
    assert sorted(p.name for p in disk.root.rglob("*") if p.is_file()) == ["filler"]  # nothing half written


def test_a_snapshot_on_a_full_disk_leaves_no_file_and_a_retry_writes_it(disk, tmp_path, context, caplog):
    caplog.set_level(logging.INFO)
    folder = disk.root / "snaps"
    config = write_config(tmp_path / "snap.toml", eyes="left", output={"snapshot_dir": str(folder)})
    with compositor(config, context, frames=3, virtual_time=True) as comp:
        run_bounded(comp)
        disk.fill()
        reply = request(comp.control.address, {"cmd": "snapshot", "path": "shown.png"})
        assert list(folder.iterdir()) == [], reply  # no empty file to block the name, no temporary one
        assert reply == {"ok": False, "error": f"cannot write {folder / 'shown.png'}: {NO_SPACE}"}
        disk.free()
        reply = request(comp.control.address, {"cmd": "snapshot", "path": "shown.png"})
        assert reply == {"ok": True, "path": str(folder / "shown.png")}
    with Image.open(folder / "shown.png") as image:
        assert image.format == "PNG" and image.size == (64, 72)
