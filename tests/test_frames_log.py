"""The per-frame log (`[output] frames_log`), back-pressure of the writers in virtual time, the Perfetto timeline
(`hmdrt export perfetto`) and the plots of a run (`hmdrt report plot`).

Virtual-time runs are at 64x72 per eye on sim-cpu with the PNG and log writers slowed down, so that a writer
that skipped what it had no time for would leave frames out (as the frame writer did before: 6-7 of 40).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import msgspec
import pytest
import zmq
from PIL import Image

from hmdrt.cli import main
from hmdrt.errors import HmdrtError
from hmdrt.present import output
from hmdrt.telemetry import frames_log
from hmdrt.telemetry.frames_log import FramesHeader, FramesLog, read_frames_log
from hmdrt.telemetry.perfetto import trace_events
from hmdrt.telemetry.plot import NEEDS_LOG, plot_run
from hmdrt.telemetry.report import FrameRecord, GazeError, SampleUse
from hmdrt.testing import compositor, run_bounded, write_config

N = 20
SLOW_S = 0.05  # each PNG and each log line takes this long: far longer than a frame at 64x72 in virtual time
WALL_CLOCK = ("frame_ms", "render_ms", "present_ms", "overhead_ms", "stages_ms")  # differ between virtual runs
PERIOD = 33_333_333
HEADER = FramesHeader(vsync_hz=30.0, period_ns=PERIOD, margin_ns=2_000_000, method="rrm", profile="sim-cpu")
MS = 1_000_000


def slowed(write):
    def slow(*args, **kwargs):
        time.sleep(SLOW_S)
        return write(*args, **kwargs)

    return slow


@dataclass
class Run:
    folder: Path
    report: dict
    shown: list[FrameRecord]


@pytest.fixture(scope="module")
def runs(tmp_path_factory) -> list[Run]:
    """Two virtual-time runs of the same config, each in a folder of its own, writing every VSync as a PNG and a
    log line through writers slower than the frames (the log's queue shortened to 2 so that it fills too)."""
    out = []
    context = zmq.Context()
    try:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(output, "write_png", slowed(output.write_png))
            patch.setattr(FramesLog, "_write", slowed(FramesLog._write))
            patch.setattr(frames_log, "QUEUE", 2)
            for name in ("a", "b"):
                folder = tmp_path_factory.mktemp(name)
                keys = {"frames_dir": "frames", "frames_log": "log/frames.jsonl", "every": 1}
                config = write_config(folder / "run.toml", output=keys)
                with compositor(config, context, frames=N, virtual_time=True) as c:
                    report, _ = run_bounded(c)
                    out.append(Run(folder, report, c.records))
    finally:
        context.destroy(linger=0)
    return out


def test_a_virtual_time_run_writes_every_frame_and_every_record(runs):
    for run in runs:
        assert run.report["frames_not_written"] == 0 and run.report["frames_log_not_written"] == 0
        assert sorted(p.name for p in (run.folder / "frames").iterdir()) == [f"vsync_{k:06d}.png" for k in range(N)]
        reading = read_frames_log(run.folder / "log" / "frames.jsonl")
        assert reading.records == run.shown and [r.vsync for r in reading.records] == list(range(N))
        assert not reading.cut and len((run.folder / "log" / "frames.jsonl").read_bytes().splitlines()) == N + 1
        header = reading.header
        assert header.virtual_time and header.period_ns == PERIOD and header.margin_ns == 2 * MS
        assert header.config == str(run.folder / "run.toml")


def test_two_virtual_time_runs_write_the_same_frames_and_log(runs):
    a, b = runs
    for png in sorted((a.folder / "frames").iterdir()):
        assert png.read_bytes() == (b.folder / "frames" / png.name).read_bytes(), png.name

    def steady(run: Run) -> list[dict]:
        lines = [json.loads(line) for line in (run.folder / "log" / "frames.jsonl").read_text().splitlines()]
        lines[0].pop("config")
        return [{k: v for k, v in line.items() if k not in WALL_CLOCK} for line in lines]

    assert steady(a) == steady(b)
    assert steady(a)[1]["gaze"]["device"] == "replay" and steady(a)[1]["level"] == 1.0


def test_a_reload_keeps_the_open_frames_log_and_names_it_as_needing_a_restart(tmp_path, context, caplog):
    path = write_config(tmp_path / "run.toml", output={"frames_log": "a.jsonl"})
    with compositor(path, context, frames=2, virtual_time=True) as comp:
        write_config(path, output={"frames_log": "b.jsonl"})
        comp._reload(str(path))
        assert comp.config.output.frames_log == str(tmp_path / "a.jsonl")
        run_bounded(comp)
    assert f"reloaded {path}; restart to change output.frames_log" in caplog.text
    assert len(read_frames_log(tmp_path / "a.jsonl").records) == 2 and not (tmp_path / "b.jsonl").exists()


@pytest.mark.usefixtures("own_signals")
def test_a_frames_log_that_cannot_be_written_is_a_one_line_error_at_start(tmp_path, capsys):
    (tmp_path / "file").write_text("")
    path = write_config(tmp_path / "run.toml", output={"frames_log": "file/frames.jsonl"})
    assert main(["run", str(path), "--frames", "3", "--virtual-time"]) == 1
    err = capsys.readouterr().err
    assert (
        err.startswith(f"hmdrt: error: output.frames_log: cannot write {tmp_path}/file/frames.jsonl")
        and err.count("\n") == 1
    )


def frame(vsync: int, shown: str = "new", frame_id: int | None = None, **fields) -> FrameRecord:
    """A frame record as a real-time run writes it, shown at VSync `vsync` (1 s + vsync periods)."""
    t = 1_000_000_000 + vsync * PERIOD
    frame_id = vsync if frame_id is None else frame_id
    values = {
        "actual_present_ns": t,
        "predicted_wake_ns": t - 28 * MS,
        "predicted_present_ns": t,
        "predicted_display_ns": t + PERIOD // 2,
        "actual_wake_ns": t - 28 * MS,
        "render_start_ns": t - 27 * MS,
        "render_end_ns": t - 4 * MS,
        "missed": False,
        "gaze": SampleUse("eye", 2 * frame_id, t - 40 * MS, 50 * MS),
        "pose": SampleUse("head", frame_id, t - 30 * MS),
        "method": "rrm",
        "params": {"fovea_deg": 10.0},
        "stages_ms": {} if shown == "repeat" else {"trace/primary": 5.0, "trace": 12.0, "shade": 3.0},
        "rays": 0 if shown == "repeat" else 1000,
        "frame_ms": 0.0 if shown == "repeat" else 24.0,
        "render_ms": 0.0 if shown == "repeat" else 20.0,
        "present_ms": 2.0 if shown == "repeat" else 0.3,
        "level": 0.75,
    }
    return FrameRecord(vsync=vsync, frame_id=frame_id, shown=shown, **{**values, **fields})


GAZE_ERRORS = [GazeError(0, 0.5, 0.75, 10.0), GazeError(1, 12.5, 12.25, 10.0)]  # of VSyncs 0 and 1, known at 2


def real_time_records() -> list[FrameRecord]:
    """Frame 0 on time, a repeat (frame 1 late), frame 1 late, frame 2, an unwarped repeat."""
    t1 = 1_000_000_000 + PERIOD
    return [
        frame(0),
        frame(1, "repeat", frame_id=0, warp_pose=SampleUse("head", 7, t1 - 5 * MS)),
        frame(2, "late", frame_id=1, missed=True, predicted_present_ns=t1, actual_wake_ns=t1 - 28 * MS,
              render_start_ns=t1 - 27 * MS, render_end_ns=t1 + 10 * MS, frame_ms=38.0, render_ms=36.0,
              gaze_errors=GAZE_ERRORS),
        frame(3, frame_id=2, actual_wake_ns=t1 + 11 * MS, render_start_ns=t1 + 12 * MS),
        frame(4, "repeat", frame_id=2, warp_skipped=True),
    ]  # fmt: skip


def write_log(path: Path, records: list[FrameRecord], header: FramesHeader = HEADER) -> Path:
    log = FramesLog(path, header)
    log.start()
    for record in records:
        log.offer(record.to_dict())
    log.close()
    return path


def test_real_time_drops_and_counts_what_virtual_time_waits_for(tmp_path, monkeypatch):
    monkeypatch.setattr(FramesLog, "_write", slowed(FramesLog._write))
    monkeypatch.setattr(frames_log, "QUEUE", 2)
    for block in (False, True):
        log = FramesLog(tmp_path / f"{block}.jsonl", HEADER, block=block)
        log.start()
        for vsync in range(12):
            log.offer(frame(vsync).to_dict())
        log.close()
        written = read_frames_log(tmp_path / f"{block}.jsonl").records
        assert len(written) + log.skipped == 12 and log.failed == 0
        assert log.skipped == 0 if block else log.skipped > 0


KILLED_WRITER = """
import sys, time
from hmdrt.telemetry.frames_log import FramesHeader, FramesLog
from hmdrt.telemetry.report import FrameRecord

log = FramesLog(sys.argv[1], FramesHeader(vsync_hz=30.0, period_ns=33333333), block=True)
log.start()
stages = {f"stage_{i}": float(i) for i in range(100)}  # lines of about 2 kB: a buffer holds a few
for vsync in range(int(sys.argv[2])):
    log.offer(FrameRecord(vsync, vsync, "new", 0, 0, 0, 0, 0, 0, 0, False, None, None, stages_ms=stages).to_dict())
while not log._queue.empty():
    time.sleep(0.01)
time.sleep(0.5)  # the last one taken from the queue is written
print("offered", flush=True)
time.sleep(60)
"""


def test_a_killed_writer_leaves_every_record_it_was_given_in_complete_lines(tmp_path):
    """SIGKILL gives the process no chance to flush: what the writer had taken must be in the file already."""
    path, count = tmp_path / "frames.jsonl", 123
    process = subprocess.Popen([sys.executable, "-c", KILLED_WRITER, str(path), str(count)], stdout=subprocess.PIPE)
    try:
        assert process.stdout.readline() == b"offered\n"
    finally:
        os.kill(process.pid, signal.SIGKILL)
        process.communicate()
    data = path.read_bytes()
    assert data.endswith(b"\n") and data.count(b"\n") == count + 1 and len(data) > 200_000
    reading = read_frames_log(path)
    assert not reading.cut and [r.vsync for r in reading.records] == list(range(count))


def test_the_reader_leaves_out_a_cut_last_line_and_names_a_bad_one(tmp_path):
    path = write_log(tmp_path / "frames.jsonl", real_time_records())
    whole = path.read_bytes()
    path.write_bytes(whole + msgspec.json.encode(frame(5).to_dict())[:100])
    reading = read_frames_log(path)
    assert reading.cut and reading.records == real_time_records()
    assert reading.gaze_errors() == {0: GAZE_ERRORS[0], 1: GAZE_ERRORS[1]}  # joined back to their own VSyncs
    lines = whole.splitlines(keepends=True)
    for bad, reason in (
        (lines[3].replace(b'"shown":"late"', b'"shown":"early"'), "shown is 'early'"),
        (lines[3].replace(b'"frame_ms":38.0', b'"frame_ms":-1.0'), "frame_ms = -1.0"),
        (lines[3].replace(b'"vsync":2', b'"vsync":1'), "out of order"),
        (lines[3].replace(b'"rays":1000', b'"rays":' + b"9" * 30), "integer beyond"),
        (lines[3].replace(b'"vsync":1,"left', b'"vsync":3,"left'), "vsync 3, neither this VSync nor an earlier"),
        (lines[3].replace(b'"left_deg":0.5', b'"left_deg":-0.5'), "left_deg = -0.5 is not an angle"),
        (b"[]\n", "Expected `object`, got `array`"),
    ):
        path.write_bytes(b"".join([*lines[:3], bad, *lines[4:]]))
        with pytest.raises(HmdrtError, match=f"^{path}:4: not a frame record: .*{reason}"):
            read_frames_log(path)
    path.write_bytes(b'{"format":"hmdrt-trace","v":1,"vsync_hz":30.0,"period_ns":1}\n')
    with pytest.raises(HmdrtError, match=f"^{path}:1: not a hmdrt-frames log"):
        read_frames_log(path)
    path.write_bytes(b"")
    with pytest.raises(HmdrtError, match="empty"):
        read_frames_log(path)
    with path.open("wb") as f:
        f.truncate(frames_log.MAX_FILE_BYTES + 1)
    with pytest.raises(HmdrtError, match="the limit is"):
        read_frames_log(path)


def ns(us: float) -> int:
    return round(us * 1000)


def check_trace(trace: dict) -> dict[str, list[dict]]:
    """Valid trace-event JSON whose spans nest on each track and whose events are in time order; the events per
    track name, each span with the span it is nested in as "parent"."""
    events = trace["traceEvents"]
    assert {e["ph"] for e in events} <= {"X", "i", "M"}
    names = {e["tid"]: e["args"]["name"] for e in events if e["ph"] == "M" and e["name"] == "thread_name"}
    assert sorted(names.values()) == ["display", "gaze samples", "pose samples", "render"]
    tracks: dict[str, list[dict]] = {name: [] for name in names.values()}
    for e in events:
        assert isinstance(e["pid"], int) and isinstance(e["tid"], int) and isinstance(e["name"], str)
        if e["ph"] == "M":
            continue
        assert e["tid"] in names and isinstance(e["ts"], int | float)
        assert e["ph"] == "i" and e["s"] in "tpg" or e["ph"] == "X" and e["dur"] >= 0
        tracks[names[e["tid"]]].append(e)
    for track in tracks.values():
        assert [ns(e["ts"]) for e in track] == sorted(ns(e["ts"]) for e in track)
        stack: list[dict] = []
        for e in (e for e in track if e["ph"] == "X"):
            start, end = ns(e["ts"]), ns(e["ts"]) + ns(e["dur"])
            while stack and start >= ns(stack[-1]["ts"]) + ns(stack[-1]["dur"]):
                stack.pop()
            if stack:
                assert end <= ns(stack[-1]["ts"]) + ns(stack[-1]["dur"]), (e, stack[-1])
            e["parent"] = stack[-1] if stack else None
            stack.append(e)
    return tracks


def test_perfetto_export_nests_stages_in_frames_and_marks_misses_repeats_and_samples(tmp_path):
    path = write_log(tmp_path / "frames.jsonl", real_time_records())
    assert main(["export", "perfetto", str(path), "--out", str(tmp_path / "run.json")]) == 0
    tracks = check_trace(json.loads((tmp_path / "run.json").read_text()))
    frames = [e for e in tracks["render"] if e["cat"] == "frame"]
    assert [e["name"] for e in frames] == ["frame 0", "frame 1 (late)", "frame 2"]
    assert all(e["parent"] is None for e in frames) and frames[1]["args"]["missed"] is True
    assert ns(frames[1]["ts"]) == 1_000_000_000 + PERIOD - 28 * MS and ns(frames[1]["dur"]) == 38 * MS
    for e in (e for e in tracks["render"] if e["cat"] == "stage"):
        parent = e["parent"]
        assert parent["cat"] == ("stage" if e["args"]["stage"] == "trace/primary" else "frame")
        assert e["args"]["cut"] is False and ns(e["dur"]) == round(e["args"]["ms"] * MS)
    assert [e["args"]["stage"] for e in tracks["render"] if e["parent"] is frames[0]] == ["trace", "shade"]
    display = tracks["display"]
    assert [e["name"] for e in display if e["ph"] == "X"] == [
        "latch frame 0", "timewarp", "latch frame 1 (late)", "latch frame 2", "repeat (warp skipped)"
    ]  # fmt: skip
    assert [e["args"]["vsync"] for e in display if e["name"] == "vsync"] == [0, 1, 2, 3, 4]
    (miss,) = [e for e in display if e["cat"] == "miss"]
    assert ns(miss["ts"]) == 1_000_000_000 + 2 * PERIOD and miss["args"]["late_ms"] == pytest.approx(PERIOD / MS)
    assert [e["args"]["seq"] for e in tracks["gaze samples"]] == [0, 2, 4]  # each sample used once
    assert sorted(e["args"]["seq"] for e in tracks["pose samples"]) == [0, 1, 2, 7]  # with the repeat's warp pose
    assert {e["args"]["device"] for e in tracks["pose samples"]} == {"head"}


def test_perfetto_export_of_a_virtual_time_run_fits_each_frame_in_its_period(runs):
    reading = read_frames_log(runs[0].folder / "log" / "frames.jsonl")
    tracks = check_trace(json.loads(json.dumps(trace_events(reading))))
    frames = [e for e in tracks["render"] if e["cat"] == "frame"]
    assert len(frames) == N and all(0 < ns(e["dur"]) <= PERIOD for e in frames)
    stages = [e for e in tracks["render"] if e["cat"] == "stage"]
    assert stages and all(e["parent"] is not None for e in stages)


def test_plots_of_a_frames_log_and_of_a_report(tmp_path, runs, capsys):
    log = write_log(tmp_path / "frames.jsonl", real_time_records())
    written, note = plot_run(log, tmp_path / "real")
    assert [p.name for p in written] == ["timeline.png", "latency.png"] and note is None
    assert Image.open(written[0]).size == (1200, 720) and Image.open(written[1]).size == (1200, 480)

    assert main(["report", "plot", str(runs[0].folder / "log" / "frames.jsonl"), "--out", str(tmp_path / "v")]) == 0
    assert {p.name for p in (tmp_path / "v").iterdir()} == {"timeline.png", "latency.png"}

    report = tmp_path / "report.json"
    report.write_text(json.dumps(runs[0].report, indent=2))
    assert main(["report", "plot", str(report), "--out", str(tmp_path / "r")]) == 0
    printed = capsys.readouterr().out
    assert "summary.png" in printed and NEEDS_LOG in printed
    assert Image.open(tmp_path / "r" / "summary.png").format == "PNG"


@pytest.mark.parametrize(
    "command, content, message",
    [
        (
            ["export", "perfetto"],
            b'{"format":"hmdrt-frames","v":1,"vsync_hz":30,"period_ns":1}\n[]\n',
            ":2: not a frame",
        ),
        (["report", "plot"], b'{"format":"hmdrt-frames","v":1}\n', ":1: not a frames log header"),
        (["report", "plot"], b'{\n  "vsync_hz": 30,\n  "frame_ms": x\n}\n', ":3: not a run report: JSON is malformed"),
    ],
)
def test_a_bad_input_file_is_a_one_line_error_naming_file_and_line(tmp_path, capsys, command, content, message):
    path = tmp_path / ("in.json" if b"\n " in content else "in.jsonl")
    path.write_bytes(content)
    assert main([*command, str(path), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and err.startswith(f"hmdrt: error: {path}{message}"), err


def test_the_report_spreads_the_new_frames_controller_levels_and_leaves_repeats_out():
    from hmdrt.telemetry.report import RunReport

    report = RunReport(30.0)
    for v, level in enumerate([1.0] * 6 + [0.3] * 4):
        report.add(frame(2 * v, level=level))
        report.add(frame(2 * v + 1, "repeat", frame_id=2 * v, level=0.1))  # a repeat renders nothing
    snapshot = report.snapshot()
    report.add(frame(20, level=0.0))
    assert snapshot.to_dict()["controller_level"] == {
        "frames": 10,
        "p10": 0.3,
        "p50": 1.0,
        "p90": 1.0,
        "share_at_least_half": 0.6,
    }
    after = report.to_dict()["controller_level"]
    assert after["frames"] == 11 and after["share_at_least_half"] == round(6 / 11, 5)
    assert RunReport(30.0).to_dict()["controller_level"] is None
    unlevelled = RunReport(30.0)
    unlevelled.add(frame(0, level=None))
    assert unlevelled.to_dict()["controller_level"] is None
