"""hmdrt's pytest plugin and hmdrt.testing: docs/testing.md's example run by pytest as a lab would run it, the
plugin's import cost, the report's attribute access and the checks' messages."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from hmdrt.compositor.config import load_config
from hmdrt.testing import (
    TRACE,
    Report,
    assert_every_vsync_shown,
    assert_latency_within,
    assert_miss_rate_at_most,
    write_config,
)

ROOT = Path(__file__).resolve().parent.parent
REPORT = {
    "vsyncs": 30,
    "vsync_hz": 30.0,
    "presented": 28,
    "re_presented": 2,
    "out_of_order": 0,
    "frames": 28,
    "deadline_misses": 1,
    "miss_rate": 0.0357,
    "miss_rate_after_warmup": 0.0,
    "latency_ms": {"gaze_to_photon": {"p50": 34.0, "p95": 40.0, "p99": 70.0, "max": 71.0}},
    "stages_ms": {"trace/secondary": 1.5},
    "controller": {"trajectory": [{"level": 1.0}, {"level": 0.5}]},
}


def test_the_docs_example_passes_under_pytest_with_the_plugin_from_its_entry_point(tmp_path):
    """docs/testing.md's test file in a project of its own (no conftest, no hmdrt checkout), run by pytest."""
    [example] = re.findall(r"```python\n(.*?)```", (ROOT / "docs" / "testing.md").read_text(), re.S)
    (tmp_path / "pytest.ini").write_text("[pytest]\n")
    (tmp_path / "test_latency_budget.py").write_text(example)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTEST_ADDOPTS", "PYTEST_DISABLE_PLUGIN_AUTOLOAD")}
    run = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "test_latency_budget.py"],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert run.returncode == 0 and "3 passed" in run.stdout, run.stdout + run.stderr


def test_the_plugin_imports_nothing_heavy():
    """A pytest run that uses no hmdrt fixture pays for neither numba nor the compositor."""
    code = (
        "import sys, hmdrt.testing.pytest_plugin\n"
        "heavy = ('numba', 'numpy', 'zmq', 'msgspec', 'hmdrt.drivers', 'hmdrt.replay', 'hmdrt.compositor',\n"
        "         'hmdrt.testing.runs')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy or m.startswith(heavy)))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stdout + out.stderr


def test_a_report_reads_by_attribute_and_by_key():
    report = Report(REPORT)
    assert report.latency_ms.gaze_to_photon.p99 == report["latency_ms"]["gaze_to_photon"]["p99"] == 70.0
    assert report.period_ms == pytest.approx(33.333, abs=1e-3) and report.stages_ms["trace/secondary"] == 1.5
    assert report.controller.trajectory[-1].level == 0.5
    assert report == REPORT and report.latency_ms == REPORT["latency_ms"] and dict(report).keys() == REPORT.keys()
    copy = report.to_dict()
    copy["latency_ms"]["gaze_to_photon"]["p99"] = 0.0
    assert report.latency_ms.gaze_to_photon.p99 == 70.0  # a copy
    with pytest.raises(AttributeError, match="the report has no 'bogus'; it has vsyncs"):
        _ = report.bogus
    with pytest.raises(AttributeError, match="no 'period_ms'; it has gaze_to_photon"):
        _ = report.latency_ms.period_ms


def test_the_checks_pass_within_their_bounds_and_say_what_failed():
    assert_every_vsync_shown(REPORT)
    assert_latency_within(REPORT, periods=2.2)  # 70 ms = 2.1 periods
    assert_latency_within(Report(REPORT), periods=1.5, percentile="p95")
    assert_miss_rate_at_most(REPORT, 0.04)
    assert_miss_rate_at_most(REPORT, 0.0, after_warmup=True)
    with pytest.raises(AssertionError, match=r"gaze_to_photon p99 70.00 ms = 2.10 periods, over 2 periods \(66.67"):
        assert_latency_within(REPORT, periods=2)
    with pytest.raises(AssertionError, match="no pose_to_photon latency"):
        assert_latency_within({**REPORT, "latency_ms": {"pose_to_photon": {"p99": None}}}, 2, "pose_to_photon")
    with pytest.raises(AssertionError, match="miss_rate 3.57% over 1.00%"):
        assert_miss_rate_at_most(REPORT, 0.01)
    with pytest.raises(AssertionError, match="30 VSyncs but 28 frames presented and 1 repeated"):
        assert_every_vsync_shown({**REPORT, "re_presented": 1})
    with pytest.raises(AssertionError, match="2 frames were shown out of order"):
        assert_every_vsync_shown({**REPORT, "out_of_order": 2})


def test_write_config_writes_a_small_private_run_fed_by_the_shipped_trace(tmp_path):
    path = write_config(tmp_path / "a.toml", {"options": {"group_w": 2}}, "left", pacing={"margin_ms": 3.0})
    run = load_config(path)
    assert (run.display.profile, run.display.resolution, run.display.eyes) == ("sim-cpu", "64x72", "left")
    assert str(run.method_choice) == "rrm?group_w=2" and run.pacing.margin_ms == 3.0
    assert run.bus.ingest == run.bus.telemetry == run.bus.control == ""  # the private ipc:// defaults
    assert [d.url for d in run.drivers] == [f"replay://{ROOT / 'configs/traces/synthetic_250hz.jsonl.gz'}?loop=1"]
    assert TRACE.is_file()  # installed with the package: a lab's tests find it too
    assert load_config(write_config(tmp_path / "b.toml", drivers=[])).drivers == []
    other = write_config(tmp_path / "c.toml", trace=tmp_path / "t.jsonl", drivers=[{"url": "synthetic://?seed=2"}])
    assert [d.url for d in load_config(other).drivers] == ["synthetic://?seed=2"]


def test_hmdrt_run_takes_a_config_file_or_config_keys_not_both(hmdrt_run, hmdrt_config):
    with pytest.raises(TypeError, match="not both"):
        hmdrt_run(hmdrt_config(), method="full")
