"""The compositor daemon against its latency budget, with real parts: the Whitted scene through the real tracer,
the recorded synthetic trace replayed by its driver, and the three bus sockets on loopback ports of their own.

Real-time runs check the per-VSync bookkeeping (every VSync shows something, on the VSync grid, in order,
never with a sample from the future) and a budget met with room to spare; virtual-time runs check that a
run is a pure function of config, trace and seed. Bounds on time are generous: the machine is shared.
"""

from __future__ import annotations

import gc
import math
import os
import sys
import time
from pathlib import Path

import numba
import numpy as np
import pytest
from PIL import Image

from hmdrt.cli import main
from hmdrt.compositor.config import load_config
from hmdrt.compositor.daemon import Compositor
from hmdrt.compositor.session import READY_RENDERED
from hmdrt.present.encode import linear_to_srgb8
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource
from hmdrt.replay.trace import write_trace
from hmdrt.testing import assert_every_vsync_shown, compositor, run_bounded, write_config
from tests.compositor_helpers import (
    WALL_CLOCK,
    assert_one_line_error,
    digest,
    receive,
    subscribe,
)

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


@pytest.mark.parametrize("foresight", [False, True])
def test_hold_budget_controller_lowers_the_quality_of_a_renderer_over_budget(hmdrt_config, hmdrt_compositor, foresight):
    settings = {"kind": "hold-budget", "foresight": foresight}
    config = hmdrt_config(eyes="left", pacing={"render_delay_ms": 40}, controller=settings)
    comp = hmdrt_compositor(config, frames=60)
    report, _ = run_bounded(comp)
    records = comp.records
    controller = report["controller"]
    levels = [entry["level"] for entry in controller["trajectory"]]
    assert controller["kind"] == "hold-budget" and levels[0] == 1.0
    assert controller["foresight"] == foresight and ("fit" in controller and "change_ms" in controller) == foresight
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
    nearest_rank = {q: sorted(new_levels)[math.ceil(q / 100 * len(new_levels)) - 1] for q in (10, 90)}
    assert spread["p90"] == round(nearest_rank[90], 2) and spread["p10"] == round(nearest_rank[10], 2)
    # feedback waits for 6 frames' times and steps down a frame at a time; foresight, which predicts each frame's time,
    # goes to the floor as soon as it has learnt one frame (presented a VSync or two after it is rendered)
    assert spread["p90"] == (0.0 if foresight else 1.0) and (controller["trajectory"][1]["frame"] <= 4) == foresight


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


def test_a_minimal_config_resolves_to_the_shipped_configs_speed_settings(tmp_path, context):
    """A config of a scene and a method renders with the settings the shipped configs/default.toml renders with:
    kernel threads chosen from the core count (1 on 2 cores), tracing on every core, the same pacing margin and
    display; so relying on "every key is optional" is not the slow way to run."""
    minimal = tmp_path / "minimal.toml"
    minimal.write_text('scene = "whitted"\n[method]\nname = "rrm"\n')
    shipped = Path(__file__).resolve().parents[1] / "configs" / "default.toml"
    resolved = {}
    for name, path in (("minimal", minimal), ("shipped", shipped)):
        threads: list[int] = []
        with compositor(path, context, frames=2, virtual_time=True) as comp:
            render = comp.session.render

            def counting(*args, render=render, threads=threads, **kwargs):
                threads.append(numba.get_num_threads())
                return render(*args, **kwargs)

            comp.session.render = counting
            run_bounded(comp)
            config = comp.config
            resolved[name] = (
                set(threads),
                comp.session.tracer.tracer.threads,
                config.pacing,
                config.display,
                config.run.kernel_threads,
            )
    assert resolved["minimal"] == resolved["shipped"]
    assert resolved["minimal"][0] == {1 if (os.cpu_count() or 1) <= 2 else numba.config.NUMBA_NUM_THREADS}


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
