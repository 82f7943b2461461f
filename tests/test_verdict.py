"""What a run is held to, said where a person reads a run: the end of `hmdrt run` and its status line, and
`hmdrt status`, each with its target and whether it was met; "n/a" where a figure does not exist yet, never None."""

from __future__ import annotations

import json

import pytest

from hmdrt.cli import main
from hmdrt.compositor.startup import Startup
from hmdrt.telemetry import verdict
from hmdrt.testing import compositor, run_bounded, write_config

REPORT = {
    "vsync_hz": 30.0,
    "miss_rate": 0.066,
    "latency_ms": {"gaze_to_photon": {"p99": 70.0}},
    "controller": {"target_miss_rate": 0.01},
    "controller_level": {"frames": 100, "share_at_least_half": 0.05},
}


def test_each_figure_is_judged_against_its_target():
    missed = verdict.line(REPORT)
    assert missed == (
        "miss rate 6.6% (target <= 1%: missed); gaze-to-photon p99 70.0 ms (target <= 66.7 ms, 2 periods: missed); "
        "controller level >= 0.5 in 5% of frames (target > 50%: missed)"
    )
    good = {**REPORT, "miss_rate": 0.004, "latency_ms": {"gaze_to_photon": {"p99": 41.0}}}
    good["controller_level"] = {"frames": 100, "share_at_least_half": 0.9}
    assert [v.met for v in verdict.verdicts(good)] == [True, True, True]
    without = {k: v for k, v in REPORT.items() if k not in ("controller", "controller_level")}
    without["latency_ms"] = {"gaze_to_photon": {"p99": None}}  # no gaze sample shown yet
    judged = verdict.verdicts(without)
    assert [v.what for v in judged] == ["miss rate", "gaze-to-photon p99"]  # the 1% bar without a controller
    assert str(judged[1]) == "gaze-to-photon p99 n/a (target <= 66.7 ms, 2 periods: n/a)"


@pytest.mark.usefixtures("own_signals")
def test_the_end_of_a_run_states_targets_and_verdicts_and_never_none(tmp_path, capsys):
    config = write_config(tmp_path / "run.toml", method="full", eyes="left", drivers=[])
    assert main(["run", str(config), "--frames", "4", "--virtual-time"]) == 0
    first, last = capsys.readouterr().out.strip().splitlines()
    assert "started: setting up the scene and the tracer" in first
    assert "compiling full's kernels and the timewarp" in first and "connecting drivers" in first
    assert "miss rate 0.0% (target <= 5%: met)" in last  # the test config's controller's target_miss_rate
    assert "gaze-to-photon p99 n/a (target <= 66.7 ms, 2 periods: n/a)" in last  # no driver: no gaze shown
    assert "None" not in last


def test_hmdrt_status_reads_as_a_person_reads_it_and_json_for_scripts(tmp_path, context, capsys):
    config = write_config(tmp_path / "status.toml", eyes="left")
    with compositor(config, context, frames=3, virtual_time=True) as comp:
        run_bounded(comp)
        assert main(["status"]) == 0
        text = capsys.readouterr().out
        assert main(["status", "--json"]) == 0
        reply = json.loads(capsys.readouterr().out)
    assert text.startswith(f"{reply['method']} on whitted at sim-cpu (30 Hz, period 33.3 ms): ")
    assert "frames on time" in text and "render estimate" in text and "budget (margin 2.0 ms)" in text
    assert "samples from replay" in text and "_ns" not in text and "{" not in text
    assert reply["pacing"]["period_ns"] == comp.session.profile.period_ns


def test_the_start_up_says_which_step_it_waits_for_and_how_long_each_took():
    startup = Startup()
    assert startup.now() == "starting"
    startup.step("compiling rrm's kernels and the timewarp")
    assert startup.now().startswith("compiling rrm's kernels and the timewarp: ")
    startup.step("connecting drivers")
    now = startup.now()
    assert now.startswith("compiling rrm's kernels and the timewarp 0 s; connecting drivers: "), now
    startup.end()
    assert startup.summary().startswith("compiling rrm's kernels and the timewarp 0.0 s, connecting drivers ")
