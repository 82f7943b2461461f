"""The compositor daemon against its latency budget, with real parts: the Whitted scene through the real tracer,
the recorded synthetic trace replayed by its driver, and the three bus sockets on loopback ports of their own.

Real-time runs check the per-VSync bookkeeping (every VSync shows something, on the VSync grid, in order,
never with a sample from the future) and a budget met with room to spare; virtual-time runs check that a
run is a pure function of config, trace and seed. Bounds on time are generous: the machine is shared.
"""

from __future__ import annotations

import gc
import hashlib
import json
import math
import selectors
import signal
import subprocess
import sys
import time
from pathlib import Path

import msgspec
import numba
import numpy as np
import pytest
import zmq
from PIL import Image

from hmdrt.cli import main
from hmdrt.compositor.config import load_config, reload_plan
from hmdrt.compositor.daemon import Compositor
from hmdrt.compositor.endpoints import request
from hmdrt.compositor.session import READY_RENDERED
from hmdrt.errors import ConfigError
from hmdrt.present.encode import linear_to_srgb8
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource
from hmdrt.replay.trace import write_trace
from hmdrt.testing import Background, assert_every_vsync_shown, compositor, run_bounded, write_config

from .helpers import reap, wait_for

# report fields measured on the wall clock, which differ between runs also in virtual time
WALL_CLOCK = ("frame_ms", "compositor_overhead_ms", "timewarp_ms", "stages_ms")
REPORT_KEYS = {
    "frames",
    "vsyncs",
    "vsync_hz",
    "presented",
    "re_presented",
    "repeat_rate",
    "late",
    "dropped",
    "out_of_order",
    "deadline_misses",
    "miss_rate",
    "frame_ms",
    "latency_ms",
    "stages_ms",
    "rays_per_frame",
    "method",
    "profile",
    "display",
    "drivers",
    "pacing",
    "image_buffers",
}
PERCENTILES = {"p50", "p95", "p99", "max"}


def digest(images: list[np.ndarray]) -> str:
    return hashlib.sha256(b"".join(np.ascontiguousarray(i).tobytes() for i in images)).hexdigest()


def subscribe(context: zmq.Context, comp: Compositor) -> zmq.Socket:
    """A SUB socket on the compositor's telemetry, known to be connected: a probe went through."""
    sub = context.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(comp.telemetry.address)
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        comp.telemetry.publish("probe", {})
        if sub.poll(50):
            return sub
    pytest.fail("the telemetry subscription never connected")


def receive(sub: zmq.Socket, topic: bytes, count: int, timeout_s: float = 10.0) -> list[dict]:
    """Up to `count` messages of `topic`, decoded; what arrived by timeout_s."""
    out, deadline = [], time.monotonic() + timeout_s
    while len(out) < count and time.monotonic() < deadline:
        if sub.poll(100):
            frames = sub.recv_multipart()
            if frames[0] == topic:
                out.append(msgspec.msgpack.decode(frames[1]))
    return out


def hmdrt(*args: str, timeout_s: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "hmdrt", *args], capture_output=True, text=True, timeout=timeout_s)


def assert_one_line_error(stderr: str, message: str) -> None:
    lines = stderr.strip().splitlines()
    assert "Traceback" not in stderr and len(lines) == 1, stderr
    assert lines[0].startswith("hmdrt: error: ") and message in lines[0], stderr


# --- real time --------------------------------------------------------------------------------------------------


def test_real_time_run_keeps_every_vsync_on_the_grid_in_order_and_within_budget(
    hmdrt_config, hmdrt_compositor, context
):
    comp = hmdrt_compositor(hmdrt_config(), frames=60)
    sub = subscribe(context, comp)
    period = comp.vsync.period_ns
    report, wall_s = run_bounded(comp)
    records = receive(sub, b"frame", report["vsyncs"])
    assert abs(period * 30 - 1e9) < 30 and report["vsync_hz"] == 30.0
    assert wall_s < 30  # 2 s of VSyncs

    # the report: every VSync accounted for, in order, and the budget met. A pacer that planned no lead would miss
    # every frame; the bound leaves room for a busy spell on a shared machine (CI saw 22% once over these 2 s).
    # The miss rate of the default config is bench/runtime.py's to measure.
    assert report["vsyncs"] == 60
    assert_every_vsync_shown(report)
    assert report["presented"] == report["frames"] >= 15  # the pacer may go to every other VSync on a busy machine
    assert report["miss_rate"] <= 0.5
    assert report["late"] <= report["deadline_misses"]
    gaze = report["latency_ms"]["gaze_to_photon"]
    # a new frame's gaze is about a period old when shown (a sample before its wake-up, a wake-up about the render
    # time before the VSync) and each repeat adds a period: p99 under 2 periods here, up to 5.5 measured
    # with three CPU hogs on two cores. Over 60 frames the p99 is the single worst frame, and one stall of the
    # shared machine put it at 12 periods once (2026-12-03), so the bound holds the p95: a pacer that lagged
    # by several periods would hold it there too
    assert 0 < gaze["p50"] < 2 * period / 1e6
    assert math.isfinite(gaze["p99"]) and gaze["p50"] <= gaze["p95"] <= gaze["p99"]
    assert gaze["p95"] < 6 * period / 1e6
    assert report["drivers"]["replay"]["samples"] > 0 and report["drivers"]["replay"]["malformed"] == 0
    assert report["rays_per_frame"] > 0 and report["stages_ms"] and report["frame_ms"]["p50"] > 0
    assert (report["method"], report["profile"], report["scene"]) == ("rrm", "sim-cpu", "whitted")
    display = {"profile": "sim-cpu", "width": 64, "height": 72, "eyes": ["left", "right"], "refresh_hz": 30.0}
    assert report["display"] == display

    # the per-VSync records on the telemetry bus: one per VSync, the same as the report counts
    assert len(records) == 60
    shown = [r["shown"] for r in records]
    assert shown.count("repeat") == report["re_presented"] and shown.count("late") == report["late"]
    vsyncs = [r["vsync"] for r in records]
    assert vsyncs == list(range(vsyncs[0], vsyncs[0] + 60))
    first = records[0]["actual_present_ns"]
    for r in records:
        assert r["actual_present_ns"] - first == (r["vsync"] - vsyncs[0]) * period  # on the VSync grid
        assert r["predicted_display_ns"] == r["predicted_present_ns"] + period // 2
        assert r["actual_wake_ns"] <= r["render_start_ns"] <= r["render_end_ns"] <= r["actual_present_ns"]
        for use in (r["gaze"], r["pose"]):
            assert use is None or use["t_host"] <= r["actual_wake_ns"]  # never a sample from the future
        if r["gaze"] is not None:
            assert r["gaze_to_photon_ms"] == pytest.approx((r["actual_present_ns"] - r["gaze"]["t_host"]) / 1e6)
        if r["shown"] == "new":
            assert not r["missed"] and r["actual_present_ns"] == r["predicted_present_ns"]
        elif r["shown"] == "late":  # its render outlasted the plan: shown at the first VSync after it ended
            assert r["missed"] and r["actual_present_ns"] > r["predicted_present_ns"]
            end = r["render_end_ns"]
            assert r["predicted_present_ns"] < end <= r["actual_present_ns"] < end + period
        else:
            assert not r["missed"] and r["rays"] == 0
    assert records[-1]["gaze"] is not None and records[-1]["pose"] is not None  # the samples did arrive
    ids = [r["frame_id"] for r in records]
    assert all(a <= b for a, b in zip(ids, ids[1:], strict=False))
    fresh = [r["frame_id"] for r in records if r["shown"] != "repeat"]
    assert len(set(fresh)) == len(fresh)  # a rendered frame is shown new once; after that it can only repeat
    for before, r in zip(records, records[1:], strict=False):
        if r["shown"] == "repeat":
            assert r["frame_id"] == before["frame_id"]


def test_a_collection_during_the_run_does_not_scan_what_start_up_built(tmp_path, context):
    """A full collection of the start-up heap stops every thread for ~120 ms; the compositor freezes it."""
    with compositor(write_config(tmp_path / "run.toml"), context, frames=3, virtual_time=True) as comp:
        run_bounded(comp)
        assert gc.get_freeze_count() > 10_000
        t0 = time.perf_counter()
        gc.collect()
        frozen_s = time.perf_counter() - t0
    assert gc.get_freeze_count() == 0  # closed: a process that goes on collects them again
    t0 = time.perf_counter()
    gc.collect()
    assert frozen_s < (time.perf_counter() - t0) / 5


def test_compositor_overhead_counts_the_render_loops_planning_and_hand_over(hmdrt_config, hmdrt_compositor):
    """Overhead is everything but the method's render: a slow plan (pacer.predict) and a slow hand-over (after
    the frame is built) both show in it, the hand-over in the next frame's."""

    def slowed(f):
        def slow(*args):
            time.sleep(0.004)
            return f(*args)

        return slow

    comp = hmdrt_compositor(hmdrt_config(), frames=20)
    comp.pacer.predict, comp.pacer.mark_render = slowed(comp.pacer.predict), slowed(comp.pacer.mark_render)
    run_bounded(comp)
    new = [r for r in comp.records if r.shown != "repeat"]
    assert len(new) >= 5
    assert new[0].overhead_ms >= 4 and all(r.overhead_ms >= 8 for r in new[1:])
    assert all(r.frame_ms >= r.render_ms + 4 for r in new)


def test_a_renderer_slower_than_the_period_drops_to_every_other_vsync_and_repeats_are_timewarped(
    hmdrt_config, hmdrt_compositor
):
    comp = hmdrt_compositor(hmdrt_config(eyes="left", pacing={"render_delay_ms": 45}), frames=40)
    report, wall_s = run_bounded(comp)
    shown = list(comp.shown)
    assert wall_s < 30  # 1.3 s of VSyncs: no stall
    assert report["vsyncs"] == 40
    assert_every_vsync_shown(report)
    assert report["re_presented"] >= 10
    assert report["repeat_rate"] == pytest.approx(report["re_presented"] / 40, abs=1e-5)
    assert report["pacing"]["vsyncs"] >= 2 and report["pacing"]["fits"] is False
    assert report["achieved_hz"] < 0.8 * report["vsync_hz"]
    assert report["frame_ms"]["p50"] >= 45
    assert report["stages_ms"]["render_delay"] >= 40
    assert report["timewarp_ms"]["p50"] is not None

    images_of = {r.frame_id: images for r, images in shown if r.shown != "repeat"}
    # a busy machine may skip a warp that would not end before the next VSync: such repeats are counted, unwarped
    repeats = [(r, images) for r, images in shown if r.shown == "repeat" and not r.warp_skipped]
    assert len(repeats) >= 5 and sum(r.warp_skipped for r, _ in shown) == report["timewarp_skipped"]
    assert all(r.warp_pose is not None and r.present_ms > 0 for r, _ in repeats)
    for r, _ in repeats:  # warped to a head pose at least as new as the one rendered, never from the future
        assert r.pose.t_host <= r.warp_pose.t_host <= r.actual_present_ns
    assert all(r.pose_to_photon_ms() < 4 * 33.4 for r, _ in repeats)
    turned = [not np.array_equal(images[0], images_of[r.frame_id][0]) for r, images in repeats]
    assert any(turned)  # the head moved between render and display: the repeat is not the frame as rendered


def test_hold_budget_controller_lowers_the_quality_of_a_renderer_over_budget(hmdrt_config, hmdrt_compositor):
    config = hmdrt_config(eyes="left", pacing={"render_delay_ms": 40}, controller={"kind": "hold-budget"})
    comp = hmdrt_compositor(config, frames=60)
    report, _ = run_bounded(comp)
    records = comp.records
    controller = report["controller"]
    levels = [entry["level"] for entry in controller["trajectory"]]
    assert controller["kind"] == "hold-budget" and levels[0] == 1.0
    assert len(levels) >= 2 and levels == sorted(levels, reverse=True) and controller["level"] < 1.0
    lowered = controller["trajectory"][-1]["knobs"]
    assert lowered["fovea_deg"] < 10.0 or lowered["group_w"] > 3
    params = [r.params for r in records if r.shown != "repeat"]
    assert params[0]["fovea_deg"] == 10.0 and params[0]["group_w"] == 3
    assert (params[-1]["fovea_deg"], params[-1]["group_w"]) == (lowered["fovea_deg"], lowered["group_w"])
    # the report's spread of levels is that of the new frames' records
    new_levels = [r.level for r in records if r.shown != "repeat"]
    spread = report["controller_level"]
    assert spread["frames"] == len(new_levels) == report["frames"]
    assert spread["share_at_least_half"] == pytest.approx(np.mean([v >= 0.5 for v in new_levels]), abs=1e-5)
    nearest_rank_p10 = sorted(new_levels)[math.ceil(0.1 * len(new_levels)) - 1]
    assert spread["p90"] == 1.0 and spread["p10"] == round(nearest_rank_p10, 2)


# --- virtual time -----------------------------------------------------------------------------------------------


def virtual_run(start, config: Path, frames: int, seed: int = 0) -> tuple[list[str], dict]:
    """The digests of the frames a virtual-time run of `config` showed, and its report; `start`: hmdrt_compositor."""
    comp = start(config, frames=frames, virtual_time=True, seed=seed)
    report, _ = run_bounded(comp)
    return [digest(images) for _, images in comp.shown], report


def test_virtual_time_runs_reproduce_bit_for_bit_and_follow_the_trace(tmp_path, hmdrt_config, hmdrt_compositor):
    hashes_a, report_a = virtual_run(hmdrt_compositor, hmdrt_config(name="a.toml"), 30)
    hashes_b, report_b = virtual_run(hmdrt_compositor, hmdrt_config(name="b.toml"), 30)
    assert len(hashes_a) == 30 and hashes_a == hashes_b
    assert report_a["vsyncs"] == 30 and report_a["re_presented"] == 0 and report_a["deadline_misses"] == 0
    assert report_a["virtual_time"] is True and report_a["drivers"]["replay"]["samples"] > 0

    def steady(report: dict) -> dict:
        return {k: v for k, v in report.items() if k not in (*WALL_CLOCK, "config")}

    assert steady(report_a) == steady(report_b)
    assert report_a["latency_ms"]["gaze_to_photon"]["p50"] is not None

    other = tmp_path / "other.jsonl"
    write_trace(other, SyntheticSource(SyntheticConfig(seed=2)).samples(count=500), "synthetic")
    hashes_c, report_c = virtual_run(hmdrt_compositor, hmdrt_config(name="c.toml", trace=other), 30)
    assert report_c["vsyncs"] == 30 and sum(a != c for a, c in zip(hashes_a, hashes_c, strict=True)) >= 20


def test_steady_state_frames_reuse_their_image_buffers(tmp_path, context):
    """Each eye renders into the buffers its pool made ready before the first VSync (two take turns in virtual
    time: the one the display shows and the one being rendered); with the frame writer on, the queue's share
    comes from the pool too and nothing is allocated beyond it."""
    config = load_config(write_config(tmp_path / "pool.toml"), frames=30, virtual_time=True)
    comp = Compositor(config, context=context)  # not Recording: it would hold every image
    try:
        report, _ = run_bounded(comp)
    finally:
        comp.close()
    ready = 2 * READY_RENDERED
    assert report["vsyncs"] == 30 and report["image_buffers"]["rendered"] == {"pooled": ready, "allocated": ready}

    write_config(tmp_path / "pool.toml", output={"frames_dir": "frames"})
    comp = Compositor(load_config(tmp_path / "pool.toml", frames=30, virtual_time=True), context=context)
    try:
        report, _ = run_bounded(comp)
    finally:
        comp.close()
    rendered = report["image_buffers"]["rendered"]
    assert len(list((tmp_path / "frames").iterdir())) + report["frames_not_written"] == 30
    assert ready <= rendered["allocated"] == rendered["pooled"] <= 2 * 16


def test_the_seed_changes_a_stochastic_method_and_only_the_seed(hmdrt_config, hmdrt_compositor):
    """kim21 draws its extra samples from the run's seed (rrm, on this scene, is the same for every seed)."""
    config = hmdrt_config("kim21", "left")
    hashes_0, _ = virtual_run(hmdrt_compositor, config, 6, seed=0)
    again, _ = virtual_run(hmdrt_compositor, config, 6, seed=0)
    hashes_1, _ = virtual_run(hmdrt_compositor, config, 6, seed=1)
    assert hashes_0 == again
    assert all(a != b for a, b in zip(hashes_0, hashes_1, strict=True))


def test_kernel_threads_set_the_render_threads_numba_threads_and_leave_the_frames_unchanged(
    tmp_path, context, hmdrt_config, hmdrt_compositor
):
    threads = []
    path = write_config(tmp_path / "k1.toml", eyes="left", run={"kernel_threads": 1})
    with compositor(path, context, frames=4, virtual_time=True) as comp:
        render = comp.session.render

        def counting(*args, **kwargs):
            threads.append(numba.get_num_threads())
            return render(*args, **kwargs)

        comp.session.render = counting
        run_bounded(comp)
        one = [digest(images) for _, images in comp.shown]
    assert threads == [1, 1, 1, 1]
    every, _ = virtual_run(hmdrt_compositor, hmdrt_config(eyes="left", name="k0.toml"), 4)  # 0: all of numba's
    assert one == every


def test_frames_dir_gets_every_nth_vsync_as_shown(tmp_path, context):
    out = tmp_path / "frames"
    config = write_config(tmp_path / "png.toml", output={"frames_dir": "frames", "every": 3})
    with compositor(config, context, frames=12, virtual_time=True) as comp:
        report, _ = run_bounded(comp)
        shown = {r.vsync: images for r, images in comp.shown}
    assert sorted(p.name for p in out.iterdir()) == [f"vsync_{k:06d}.png" for k in (0, 3, 6, 9)]
    assert report["frames_not_written"] == 0
    for k in (0, 3, 6, 9):
        png = np.asarray(Image.open(out / f"vsync_{k:06d}.png"))
        assert png.shape == (72, 2 * 64, 3)  # both eyes side by side
        np.testing.assert_array_equal(png, linear_to_srgb8(np.concatenate(shown[k], axis=1)))


def test_video_holds_every_nth_vsync_as_shown_at_the_display_rate(tmp_path, context):
    """H.264 is lossy: each video frame is the shown frame within a few levels, and nearer to it than to the
    frames shown before and after; an odd height is padded, not resized."""
    imageio = pytest.importorskip("imageio.v2")
    config = write_config(
        tmp_path / "video.toml", display={"resolution": "64x71"}, output={"video": "out/run.mp4", "every": 2}
    )
    with compositor(config, context, frames=16, virtual_time=True) as comp:
        report, _ = run_bounded(comp)
        shown = [linear_to_srgb8(np.concatenate(images, axis=1)) for r, images in comp.shown if r.vsync % 2 == 0]
    assert report["frames_not_written"] == 0 and len(shown) == 8
    with imageio.get_reader(tmp_path / "out" / "run.mp4") as reader:
        assert reader.get_meta_data()["fps"] == pytest.approx(15.0)
        frames = list(reader.iter_data())  # list(reader) would ask its length: inf for ffmpeg
    assert len(frames) == 8 and all(f.shape == (72, 128, 3) for f in frames)
    for i, frame in enumerate(frames):  # an odd height padded by repeating the last row
        errors = [np.abs(frame[:71].astype(int) - s.astype(int)).mean() for s in shown]
        assert errors[i] < 15 and errors[i] == min(errors)  # 4-9 levels here; the frames shown next to it 30+


def test_video_without_its_extra_is_a_one_line_error(tmp_path, capsys, own_signals, monkeypatch):
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)  # as if the video extra were not installed
    path = write_config(tmp_path / "video.toml", output={"video": "run.mp4"})
    assert main(["run", str(path), "--frames", "3", "--virtual-time"]) == 1
    assert_one_line_error(capsys.readouterr().err, "output.video needs imageio and imageio-ffmpeg: pip install")
    assert not (tmp_path / "run.mp4").exists()


def test_a_video_in_a_folder_that_is_a_file_is_a_one_line_error(tmp_path, capsys, own_signals):
    (tmp_path / "out").write_text("not a folder")
    path = write_config(tmp_path / "video.toml", output={"video": "out/run.mp4"})
    assert main(["run", str(path), "--frames", "3", "--virtual-time"]) == 1
    assert_one_line_error(capsys.readouterr().err, "output.video: cannot write")


# --- the command line and the control socket ------------------------------------------------------------------


def readline(process: subprocess.Popen, timeout_s: float) -> str:
    with selectors.DefaultSelector() as sel:
        sel.register(process.stdout, selectors.EVENT_READ)
        if not sel.select(timeout_s):
            pytest.fail(f"no output from {process.args} within {timeout_s} s")
    return process.stdout.readline()


def start_run(config: Path, report: Path) -> subprocess.Popen:
    """`hmdrt run CONFIG --report REPORT` in its own process, its output piped as text."""
    return subprocess.Popen(
        [sys.executable, "-m", "hmdrt", "run", str(config), "--report", str(report)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def test_sigterm_mid_run_writes_a_complete_report_and_exits_0(tmp_path):
    config, out = write_config(tmp_path / "run.toml"), tmp_path / "out" / "report.json"
    process = start_run(config, out)
    try:
        line = readline(process, 60)
        assert line.startswith(f"hmdrt run {config}: rrm on whitted at sim-cpu (30 Hz)"), line
        control = line.rsplit("control ", 1)[1].strip()

        def shown_some() -> bool:
            shown = request(control, {"cmd": "status"})["shown"]
            return shown["new"] + shown["late"] >= 5

        assert wait_for(shown_some, timeout_s=30)
        process.send_signal(signal.SIGTERM)
        stdout, stderr = process.communicate(timeout=30)
    finally:
        reap(process)
    assert process.returncode == 0, stderr
    assert "Traceback" not in stderr
    report = json.loads(out.read_text())
    assert REPORT_KEYS <= set(report)
    assert report["frames"] >= 5 and report["presented"] + report["re_presented"] == report["vsyncs"]
    assert set(report["frame_ms"]) == PERCENTILES and report["frame_ms"]["p50"] > 0
    for kind in ("gaze_to_photon", "pose_to_photon"):
        assert set(report["latency_ms"][kind]) == PERCENTILES and report["latency_ms"][kind]["p99"] > 0
    assert report["method"] == "rrm" and report["profile"] == "sim-cpu" and report["vsync_hz"] == 30.0
    assert report["drivers"]["replay"]["samples"] > 0 and report["rays_per_frame"] > 0
    assert f"{report['vsyncs']} VSyncs" in stdout and str(out) in stdout


def test_control_socket_status_set_snapshot_and_shutdown(tmp_path, context):
    config_file = write_config(tmp_path / "ctl.toml", output={"snapshot_dir": "snaps"})
    with compositor(config_file, context, duration_s=120) as comp:
        run = Background(comp)
        control = comp.control.address
        assert control.startswith("ipc://") and control.endswith(".sock")
        # a frame shown on time, not only late ones and repeats: on a busy machine the first few may all be late
        assert wait_for(lambda: len(comp.records) >= 3 and any(r.shown == "new" for r in comp.records), timeout_s=30)

        status = request(control, {"cmd": "status"})
        assert status["ok"] and status["method"] == "rrm" and status["profile"] == "sim-cpu"
        assert status["params"]["group_w"] == 3 and status["vsync_hz"] == 30.0
        assert status["devices"] == {"gaze": ["replay"], "pose": ["replay"]} and status["shown"]["new"] >= 1
        assert status["endpoints"] == {
            "ingest": comp.ingest.address,
            "telemetry": comp.telemetry.address,
            "control": control,
        }
        stats = request(control, {"cmd": "stats"})
        assert stats["ok"] and stats["report"]["vsyncs"] >= 3 and stats["report"]["method"] == "rrm"

        # set: the new parameters reach the frames rendered after it
        before = len(comp.records)
        reply = request(control, {"cmd": "set", "params": {"group_w": 2}})
        assert reply["ok"] and "group_w=2" in reply["method"]
        assert wait_for(lambda: any(r.params["group_w"] == 2 for r in comp.records[before:]), timeout_s=30)
        assert all(r.params["group_w"] == 3 for r in comp.records[:before])
        status = request(control, {"cmd": "status"})
        assert status["params"]["group_w"] == 2 and "group_w=2" in status["method"]

        # bad requests get an error reply, and the run goes on unchanged
        for bad, message in [
            ({"cmd": "set", "method": "nosuch"}, "unknown method 'nosuch'"),
            ({"cmd": "set", "params": {"group_w": 0}}, "group_w"),
            ({"cmd": "set", "params": {"bogus": 1}}, "bogus"),
            ({"cmd": "set", "params": "group_w=2"}, "set takes"),
            ({"cmd": "set"}, "set takes"),
            ({"cmd": "snapshot", "path": "snap.jpg"}, "snapshot takes"),
            ({"cmd": "explode"}, "unknown command 'explode'"),
        ]:
            reply = request(control, bad)
            assert reply["ok"] is False and message in reply["error"], (bad, reply)
        raw = context.socket(zmq.REQ)
        raw.setsockopt(zmq.LINGER, 0)
        raw.connect(control)
        raw.send(b"\xc1 not msgpack")
        assert raw.poll(5000) and msgspec.msgpack.decode(raw.recv())["ok"] is False
        raw.close()
        count = len(comp.records)
        assert wait_for(lambda: len(comp.records) >= count + 3, timeout_s=30)
        assert request(control, {"cmd": "status"})["params"]["group_w"] == 2

        # snapshot: the images shown, both eyes side by side, in [output] snapshot_dir
        snap = tmp_path / "snaps" / "now.png"
        reply = request(control, {"cmd": "snapshot", "path": "now.png"})
        assert reply == {"ok": True, "path": str(snap)}
        with Image.open(snap) as image:
            assert image.size == (2 * 64, 72) and np.asarray(image).std() > 5

        # the status command line against it
        printed = hmdrt("status", "--control", control)
        assert printed.returncode == 0, printed.stderr
        assert printed.stdout.startswith("rrm?") and "group_w=2" in printed.stdout
        assert "on whitted at sim-cpu (30 Hz)" in printed.stdout and "devices replay;" in printed.stdout
        printed = hmdrt("status", "--control", control, "--json")
        assert printed.returncode == 0 and json.loads(printed.stdout)["endpoints"]["control"] == control

        t0 = time.monotonic()
        assert request(control, {"cmd": "shutdown"}) == {"ok": True}
        report, _ = run.join(30)
        assert time.monotonic() - t0 < 5
    assert report["vsyncs"] >= 6 and "group_w=2" in report["method_spec"]
    assert report["presented"] + report["re_presented"] == report["vsyncs"]


def test_reload_applies_the_method_and_reports_what_needs_a_restart(tmp_path, context):
    path = write_config(tmp_path / "hup.toml", eyes="left")
    with compositor(path, context, duration_s=120) as comp:
        sub = subscribe(context, comp)
        run = Background(comp)
        assert wait_for(lambda: len(comp.records) >= 3, timeout_s=30)
        # a new method, a new display and a video (its rate is the run's)
        write_config(path, method={"options": {"group_w": 2}}, eyes="both", output={"video": "run.mp4"})
        before = len(comp.records)
        comp.reload()
        [log] = receive(sub, b"log", 1)
        restart = "display, output.video and output.every"
        assert log["level"] == "warning" and log["message"] == f"reloaded {path}; restart to change {restart}"
        assert comp.config.output.video == ""
        assert wait_for(lambda: any(r.params["group_w"] == 2 for r in comp.records[before:]), timeout_s=30)
        assert request(comp.control.address, {"cmd": "status"})["method"] == "rrm?group_w=2"

        path.write_text("[method\n")
        comp.reload()
        [log] = receive(sub, b"log", 1)
        assert log["level"] == "error" and log["message"].startswith(f"reload failed: {path} is not valid TOML")
        count = len(comp.records)
        assert wait_for(lambda: len(comp.records) >= count + 3, timeout_s=30)  # the run goes on as it was
        record, images = comp.shown[-1]
        assert record.params["group_w"] == 2
        assert [i.shape for i in images] == [(72, 64, 3)]  # still one eye: the display needs a restart
        comp.stop.set()
        report, _ = run.join(30)
    assert report["method_spec"] == "rrm?group_w=2" and report["out_of_order"] == 0


def test_reload_applies_the_pacing_margin(tmp_path, context):
    path = write_config(tmp_path / "hup.toml", eyes="left")
    with compositor(path, context, duration_s=120) as comp:
        run = Background(comp)
        assert wait_for(lambda: len(comp.records) >= 3, timeout_s=30)
        write_config(path, eyes="left", pacing={"margin_ms": 5.0})
        comp.reload()
        applied = wait_for(lambda: comp.config.pacing.margin_ms == 5.0, timeout_s=30)
        pacing = request(comp.control.address, {"cmd": "status"})["pacing"]
        comp.stop.set()
        run.join(30)
    assert applied and pacing["margin_ns"] == 5_000_000


def test_status_without_a_compositor_is_a_one_line_error():
    r = hmdrt("status", "--control", "tcp://127.0.0.1:1", "--timeout", "0.5")
    assert r.returncode != 0
    assert_one_line_error(r.stderr, "no hmdrt compositor answered at tcp://127.0.0.1:1")


# --- bad input --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "text, message",
    [
        ("bogus = 1\n", "unknown field `bogus`"),
        ("[display]\nbogus = 1\n", "unknown field `bogus` - at `$.display`"),
        ("[run]\nframes = -1\n", "$.run.frames"),
        ("[display\n", "is not valid TOML"),
    ],
)
def test_load_config_rejects_bad_files_in_one_line(tmp_path, text, message):
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError, match="^[^\n]*$") as info:
        load_config(path)
    assert message in str(info.value) and str(path) in str(info.value)


def test_a_reload_plan_keeps_what_needs_a_restart_and_names_it(tmp_path):
    old = load_config(write_config(tmp_path / "old.toml", output={"video": "run.mp4"}))
    same, restart = reload_plan(old, old)
    assert same == old and restart == []
    new = load_config(
        write_config(
            tmp_path / "new.toml",
            method={"options": {"group_w": 2}},
            eyes="left",
            output={"video": "other.mp4", "every": 2},
            pacing={"margin_ms": 3.0},
            run={"seed": 7},
        )
    )
    config, restart = reload_plan(old, new)
    assert restart == ["display", "output.video and output.every"]
    assert (config.display, config.bus, config.run) == (old.display, old.bus, old.run)
    assert (config.output.video, config.output.every) == (old.output.video, old.output.every)
    assert config.pacing.margin_ms == 3.0 and str(config.method_choice) == "rrm?group_w=2"


def test_load_config_of_a_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="config not found: .*missing.toml"):
        load_config(tmp_path / "missing.toml")


@pytest.mark.parametrize(
    "section, keys, message",
    [
        ("method", {"name": "nosuch"}, "unknown method 'nosuch'; methods: full, regular, rrm"),
        ("method", {"options": {"group_w": 0}}, "method 'rrm': Expected `int` >= 1 - at `$.group_w`"),
        ("method", {"options": {"nope": 1}}, "unknown field `nope` (options: fovea_deg"),
        ("display", {"resolution": "64by72"}, "display.resolution must be WIDTHxHEIGHT"),
        ("display", {"profile": "nosuch"}, "unknown profile 'nosuch'"),
        ("bus", {"control": "nonsense"}, "cannot bind nonsense"),
        ("drivers", [{"url": "bogus://x"}], "no driver for bogus://"),
        ("drivers", [{"url": "replay://missing.jsonl"}], "trace not found"),
        ("run", {"kernel_threads": 256}, "run.kernel_threads = 256: numba has"),
    ],
)
def test_hmdrt_run_on_a_bad_config_is_a_one_line_error(tmp_path, capsys, own_signals, section, keys, message):
    path = write_config(tmp_path / "bad.toml", **{section: keys})
    assert main(["run", str(path), "--frames", "3", "--virtual-time"]) == 1
    captured = capsys.readouterr()
    assert captured.out == ""
    assert_one_line_error(captured.err, message)


def test_hmdrt_run_on_a_missing_config_exits_non_zero_without_a_traceback(tmp_path):
    r = hmdrt("run", str(tmp_path / "missing.toml"))
    assert r.returncode == 1 and r.stdout == ""
    assert_one_line_error(r.stderr, f"config not found: {tmp_path / 'missing.toml'}")


def test_a_margin_longer_than_the_period_is_a_one_line_error(tmp_path, capsys, own_signals):
    path = write_config(tmp_path / "margin.toml", pacing={"margin_ms": 40.0})  # the period is 33.3 ms
    assert main(["run", str(path), "--frames", "3", "--virtual-time"]) == 1
    assert_one_line_error(capsys.readouterr().err, "margin")


def test_a_frames_dir_that_is_a_file_is_a_one_line_error(tmp_path, capsys, own_signals):
    (tmp_path / "frames").write_text("not a folder")
    path = write_config(tmp_path / "png.toml", output={"frames_dir": "frames"})
    assert main(["run", str(path), "--frames", "3", "--virtual-time"]) == 1
    assert_one_line_error(capsys.readouterr().err, "frames")


def test_a_frame_that_cannot_be_written_is_reported_without_a_traceback(tmp_path):
    (tmp_path / "frames" / "vsync_000000.png").mkdir(parents=True)  # in the way of the first frame
    path = write_config(tmp_path / "png.toml", eyes="left", output={"frames_dir": "frames"})
    r = hmdrt("run", str(path), "--frames", "5", "--virtual-time")
    assert "Traceback" not in r.stderr, r.stderr
    assert "cannot write" in r.stdout + r.stderr


def test_the_warm_up_compiles_every_kernel_a_frame_uses():
    """A kernel compiled mid-run holds the GIL for a fraction of a second: every thread stalls, frames miss
    and the gaze shown ages. After the warm-up (in a fresh process, so that no earlier test has compiled
    them), frames at other gazes and sizes of sample batch compile no new kernel signature."""
    code = (
        "import sys, numpy as np\n"
        "from numba.core.registry import CPUDispatcher\n"
        "from hmdrt.compositor.config import load_config, reload_plan; from hmdrt.compositor.session import Session\n"
        "from hmdrt.compositor.samples import GazeEstimate; from hmdrt.telemetry.stats import FrameStats\n"
        "def signatures():\n"
        "    return {(m, k): len(v.signatures) for m, mod in list(sys.modules.items()) if m.startswith('hmdrt')\n"
        "            for k, v in vars(mod).items() if isinstance(v, CPUDispatcher)}\n"
        "s = Session(load_config('configs/default.toml')); s.warm_up(); before = signatures()\n"
        "for f, yaw in enumerate((0.0, 0.3, -0.5, 0.6)):\n"
        "    g = np.array([yaw, 0.1, -1.0]); g /= np.linalg.norm(g)\n"
        "    s.render(f + 1, GazeEstimate(g, g, None, 0, 0, 0, 0, 0.0, 'x'), None, 0, FrameStats())\n"
        "after = signatures(); s.close()\n"
        "print(len(before), sorted(k for k, n in after.items() if n > before.get(k, 0)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    count, compiled = out.stdout.split(" ", 1)
    assert int(count) > 10  # the kernels were found
    assert compiled.strip() == "[]", f"compiled after the warm-up: {compiled}"
