"""Links that another user placed where hmdrt will write (hmdrt.files.atomic): every writer replaces the link, or
refuses the name, and never writes through it, so the file it points to is untouched.

The links are made by uid 65534 in a forked child, in a folder anyone may write in that is not sticky (in a sticky
one the kernel's protected_symlinks would refuse to follow them anyway, hiding a writer that follows links).
"""

from __future__ import annotations

import json
import os
import stat
import threading
from pathlib import Path

import pytest
from PIL import Image

from hmdrt.cli import main
from hmdrt.files.atomic import open_replacing, write_atomic
from hmdrt.replay.recorder import Recorder
from hmdrt.replay.trace import read_trace
from hmdrt.telemetry.frames_log import read_frames_log
from hmdrt.testing import ANY_PORT, write_config

NOBODY = 65534
VICTIM = b"another user's file, not hmdrt's to write"


def plant(folder: Path, names: list[str]) -> dict[str, Path]:
    """As uid 65534, a link at each name (relative to `folder`, whose subfolders are made writable by anyone) to a
    file of its own outside `folder`; the links' targets by name."""
    if os.geteuid() != 0:
        pytest.skip("placing links as another user needs root: a forked child calls setuid(65534)")
    victims = folder.parent / "victims"
    victims.mkdir(exist_ok=True)
    targets = {}
    for i, name in enumerate(names):
        targets[name] = victims / f"target-{i}"
        targets[name].write_bytes(VICTIM)
        parts = Path(name).parent.parts
        for sub in (folder.joinpath(*parts[:depth]) for depth in range(len(parts) + 1)):
            sub.mkdir(exist_ok=True)
            sub.chmod(0o777)
    pid = os.fork()
    if pid == 0:  # the other user: in the folder first, as a user who could not reach it through tmp_path's parents
        code = 1
        try:
            os.chdir(folder)
            os.setgroups([])
            os.setgid(NOBODY)
            os.setuid(NOBODY)
            for name, target in targets.items():
                os.symlink(target, name)
            code = 0
        finally:
            os._exit(code)
    assert os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]) == 0
    assert all(os.lstat(folder / name).st_uid == NOBODY for name in names)
    return targets


def check_untouched(folder: Path, targets: dict[str, Path]) -> None:
    """Every target still holds what it held, each name is now hmdrt's regular file, and no temporary file is left."""
    for name, target in targets.items():
        assert target.read_bytes() == VICTIM, name
        assert stat.S_ISREG(os.lstat(folder / name).st_mode), name
    assert not [p for p in folder.rglob(".*")], "a temporary file was left"


@pytest.mark.usefixtures("own_signals")
def test_a_run_its_plots_and_its_timeline_replace_links_and_leave_their_targets(tmp_path, capsys):
    folder = tmp_path / "shared"
    names = [
        "frames/vsync_000000.png",
        "frames/vsync_000002.png",
        "log/frames.jsonl",
        "report.json",
        "run.mp4",
        "plots/timeline.png",
        "plots/latency.png",
        "trace.json",
    ]
    targets = plant(folder, names)
    output = {"frames_dir": "frames", "frames_log": "log/frames.jsonl", "video": "run.mp4", "report": "report.json"}
    config = write_config(folder / "run.toml", eyes="left", output=output)
    assert main(["run", str(config), "--frames", "3", "--virtual-time"]) == 0
    assert [r.vsync for r in read_frames_log(folder / "log/frames.jsonl").records] == [0, 1, 2]
    assert json.loads((folder / "report.json").read_text())["vsyncs"] == 3
    with Image.open(folder / "frames/vsync_000002.png") as image:
        assert image.format == "PNG" and image.size == (64, 72)
    assert (folder / "run.mp4").read_bytes()[4:8] == b"ftyp"  # an MP4 file, written by ffmpeg
    log = str(folder / "log/frames.jsonl")
    assert main(["report", "plot", log, "--out", str(folder / "plots")]) == 0
    assert main(["export", "perfetto", log, "--out", str(folder / "trace.json")]) == 0
    assert json.loads((folder / "trace.json").read_text())["traceEvents"]
    capsys.readouterr()
    check_untouched(folder, targets)


def test_a_rendered_sequence_replaces_links_at_its_frames_log_and_stats(tmp_path, capsys):
    folder = tmp_path / "shared"
    targets = plant(folder, ["render/frame_00000.png", "render/frames.jsonl", "stats.json"])
    out, stats = folder / "render", folder / "stats.json"
    args = ["--scene", "whitted", "--profile", "sim-cpu", "--method", "full", "--resolution", "16x18"]
    assert main(["render", *args, "--frames", "2", "--out", str(out), "--stats", str(stats)]) == 0
    assert len((out / "frames.jsonl").read_text().splitlines()) == 2 and json.loads(stats.read_text())["frames"] == 2
    assert Image.open(out / "frame_00000.png").size == (16, 18)
    capsys.readouterr()
    check_untouched(folder, targets)


def test_files_written_whole_or_opened_new_replace_links_or_refuse_the_name(tmp_path):
    folder = tmp_path / "shared"
    targets = plant(folder, ["replaced.json", "kept.key", "opened.jsonl", "recording.jsonl"])
    write_atomic(folder / "replaced.json", b"{}")
    with pytest.raises(FileExistsError):  # as a key without --force, and a snapshot: the name is taken
        write_atomic(folder / "kept.key", b"secret", mode=0o600, replace=False)
    assert (folder / "kept.key").is_symlink()
    with open_replacing(folder / "opened.jsonl", b"first\n") as f:
        f.write(b"second\n")
    assert (folder / "opened.jsonl").read_bytes() == b"first\nsecond\n"

    recorder = Recorder(ANY_PORT, folder / "recording.jsonl")  # `hmdrt record`
    stop = threading.Event()
    stop.set()
    recorder.run(stop)
    assert read_trace(folder / "recording.jsonl").samples == []

    assert (folder / "replaced.json").read_bytes() == b"{}"
    targets.pop("kept.key")
    assert (tmp_path / "victims" / "target-1").read_bytes() == VICTIM
    check_untouched(folder, targets)
