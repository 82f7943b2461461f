"""The compositor from the command line and its control socket: SIGTERM, status, set, snapshot, shutdown and
reload, and bad configs as one-line errors (the runs themselves: test_runtime.py)."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import msgspec
import numpy as np
import pytest
import zmq
from PIL import Image

from hmdrt.cli import main
from hmdrt.compositor.config import load_config, reload_plan
from hmdrt.compositor.endpoints import request
from hmdrt.errors import ConfigError
from hmdrt.testing import Background, compositor, write_config
from tests.compositor_helpers import (
    PERCENTILES,
    REPORT_KEYS,
    assert_one_line_error,
    hmdrt,
    readline,
    receive,
    start_run,
    subscribe,
)

from .helpers import reap, wait_for

# --- the command line and the control socket ------------------------------------------------------------------


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
        assert "on whitted at sim-cpu (30 Hz, period 33.3 ms)" in printed.stdout and "from replay" in printed.stdout
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


@pytest.mark.parametrize("method", ["rrm", "weier16", "kim21"])
def test_the_warm_up_compiles_every_kernel_a_frame_uses(method):
    """A kernel compiled mid-run holds the GIL for a fraction of a second: every thread stalls, frames miss
    and the gaze shown ages. After the warm-up (in a fresh process, so that no earlier test has compiled
    them), frames at other gazes and sizes of sample batch compile no new kernel signature: the default config's
    method, and temporal methods whose stages that need a history run from their second frame."""
    code = (
        "import sys, msgspec, numpy as np\n"
        "from numba.core.registry import CPUDispatcher\n"
        "from hmdrt.compositor.config import load_config, reload_plan; from hmdrt.compositor.session import Session\n"
        "from hmdrt.compositor.samples import GazeEstimate; from hmdrt.telemetry.stats import FrameStats\n"
        "def signatures():\n"
        "    return {(m, k): len(v.signatures) for m, mod in list(sys.modules.items()) if m.startswith('hmdrt')\n"
        "            for k, v in vars(mod).items() if isinstance(v, CPUDispatcher)}\n"
        "config = load_config('configs/default.toml')\n"
        f"config = msgspec.structs.replace(config, method=msgspec.structs.replace(config.method, name={method!r}))\n"
        "s = Session(config); s.warm_up(); before = signatures()\n"
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


def test_a_method_that_cannot_render_the_small_frames_is_warmed_up_at_the_display_size(tmp_path, caplog):
    """The warm-up's frames against an empty scene only save time: a method that refuses their size is logged and
    still warmed up at the display's size, where the run renders it."""
    from hmdrt.compositor.session import COMPILE_SIZE, Session
    from hmdrt.foveation.reference import Full
    from hmdrt.foveation.registry import register, unregister

    sizes = []

    @register
    class Wide(Full):
        name = "wide_only"

        def render(self, request, stats, out=None):
            sizes.append(request.camera.width)
            if request.camera.width <= COMPILE_SIZE[0]:
                raise ValueError("wide_only renders 64 pixels across or more")
            return super().render(request, stats, out)

    try:
        session = Session(load_config(write_config(tmp_path / "run.toml", "wide_only")))
        try:
            with caplog.at_level("WARNING", logger="hmdrt.compositor.session"):
                session.warm_up()
        finally:
            session.close()
    finally:
        unregister("wide_only")
    assert "compiling wide_only ahead at 32x36 failed (wide_only renders 64 pixels across or more)" in caplog.text
    assert sizes == [COMPILE_SIZE[0]] + [64] * 4  # the first small frame, then two frames of both eyes at 64x72
