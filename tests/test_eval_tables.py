"""hmdrt eval's rows and the papers' tables: the methods' metrics averaged into the rows and checked where they
come back from elsewhere, kim2021's ray count and reuse, smith2013's averaged frame rates, and the date, commit
and machine under each table (the end-to-end run of the tables: test_eval.py)."""

from __future__ import annotations

import csv
import math
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest

from hmdrt.errors import HmdrtError
from hmdrt.evaluate import provenance, runner, validate
from hmdrt.evaluate.config import load_eval_config
from hmdrt.evaluate.groups import Crops, GroupResult, GroupShape
from hmdrt.evaluate.results import write_results
from hmdrt.evaluate.tables import kim2021, latency, paper_tables, smith2013
from hmdrt.foveation import METHODS, FrameRequest, MethodChoice
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import eye_cameras

EVAL = """
scenes = ["whitted"]
resolution = "32x36"
frames = 4
warmup_frames = 1
timing_rounds = 1  # the images are under test here, not the times
truth_spp = 2
cache_dir = "cache"

[[methods]]
name = "full"
"""


def _lines(markdown: str) -> list[list[str]]:
    """The body rows of a Markdown table."""
    lines = [line for line in markdown.splitlines() if line.startswith("|")][2:]
    return [[c.strip() for c in line.strip("|").split("|")] for line in lines]


def test_every_number_a_method_reports_is_averaged_over_the_scored_frames_into_the_row(tmp_path, monkeypatch):
    """A metric reported on some scored frames is averaged over those; what is not a finite number is left out;
    the warm-up frames count for nothing. The CSV has each as a metric_NAME column."""
    real = MethodChoice.make

    def reporting(choice, tracer):
        method = real(choice, tracer)
        render = method.render

        def counted(request, stats):
            image = render(request, stats)
            stats.metrics.update(frame=request.frame, label="text", broken=math.nan, flag=request.frame == 2)
            if request.frame % 2:
                stats.metrics["odd"] = 10 * request.frame
            return image

        method.render = counted
        return method

    monkeypatch.setattr(MethodChoice, "make", reporting)
    path = tmp_path / "e.toml"
    path.write_text(EVAL)
    config = load_eval_config(path)
    evaluation = runner.evaluate(config, progress=False)
    [row] = evaluation.rows
    assert row["frames"] == 3  # frames 1, 2 and 3 scored
    assert row["metrics"] == {"frame": 2.0, "flag": pytest.approx(1 / 3, abs=1e-5), "odd": 20.0}
    write_results(evaluation, config, tmp_path / "out", with_plots=False)
    with open(tmp_path / "out" / "results.csv") as f:
        [written] = list(csv.DictReader(f))
    assert (written["metric_frame"], written["metric_odd"]) == ("2.0", "20.0") and "metrics" not in written


@pytest.mark.parametrize("name", list(METHODS))
def test_every_methods_metrics_pass_the_checks_of_rows_from_elsewhere(name):
    """What a method reports is what validate lets back from a Dask worker: lower-case names, not too many."""
    profile = get_profile("sim-cpu").with_resolution_text("32x36")
    camera = eye_cameras(profile, Pose.looking([0.0, 1.6, 2.0], 0.0, 0.0), ("left",))["left"]
    with Whitted(load_scene("whitted")) as tracer:
        method = MethodChoice.parse(name).make(tracer)
        for frame in range(2):  # the second with a history
            stats = FrameStats()
            method.render(FrameRequest(camera, np.array([0.0, 0.0, -1.0]), frame), stats)
    assert len(stats.metrics) <= validate.MAX_METRICS
    assert all(validate.METRIC_NAME.fullmatch(k) for k in stats.metrics), list(stats.metrics)


def _row(label: str, **columns) -> dict:
    """A row with every column the validator asks for."""
    row: dict = {"scene": "s", "profile": "p", "trace": "t", "label": label, "method": label}
    for name, kinds in validate.COLUMNS.items():
        if name not in row:
            kind = kinds[-1]
            row[name] = "" if kind is str else {} if kind is dict else kind(1)
    return {**row, **provenance.stamp(), **columns}


def _result(row: dict) -> GroupResult:
    image = np.zeros((2, 3, 3), np.float32)
    return GroupResult([row], Crops("s", "p", "t", image, {row["label"]: image}, (1.0, 1.0)))


SHAPE = GroupShape({"scene": "s", "profile": "p", "trace": "t"}, ["a"], (2, 3))


@pytest.mark.parametrize(
    "columns, why",
    [
        ({"metrics": {f"m{k}": 1.0 for k in range(validate.MAX_METRICS + 1)}}, "65 metrics, more than 64"),
        ({"metrics": {"Bad Name": 1.0}}, "metric 'Bad Name' is not a lower-case name"),
        ({"metrics": {"x" * 65: 1.0}}, "is not a lower-case name"),
        ({"metrics": {"m": math.inf}}, "metric 'm' is not a finite number"),
        ({"metrics": {"m": math.nan}}, "metric 'm' is not a finite number"),
        ({"metrics": {"m": True}}, "metric 'm' is not a finite number"),
        ({"metrics": {"m": "1"}}, "metric 'm' is not a finite number"),
        ({"metrics": [1.0]}, "metrics is a list"),
        ({"date": "yesterday"}, "date 'yesterday' is not YYYY-MM-DD"),
        ({"commit": "abc\n| x"}, "commit 'abc\\n| x' is not a short hash"),
        ({"commit": 7}, "commit is a int"),
        ({"machine": "two\nlines"}, "machine is not one printable line"),
        ({"machine": "x" * (provenance.MAX_TEXT + 1)}, "machine is not one printable line"),
        ({"machine": ""}, "machine is not one printable line"),
    ],
)
def test_rows_from_elsewhere_with_bad_metrics_or_provenance_are_refused_in_one_line(columns, why):
    assert validate.group_result("task-1", _result(_row("a")), SHAPE).rows[0]["label"] == "a"
    with pytest.raises(HmdrtError) as err:
        validate.group_result("task-1", _result(_row("a", **columns)), SHAPE)
    assert str(err.value).startswith("task task-1: ") and why in str(err.value) and "\n" not in str(err.value)


def _kim_row(label: str, method: str, rays: int, ms: float, **columns) -> dict:
    bands = {f"psnr_{b}": 30.0 for b in ("fovea", "parafovea", "perifovea", "near_periphery")}
    comparison = {"baseline": None, "speedup_vs_baseline": None, "psnr_fovea_vs_baseline": None}
    return {"scene": "s", "profile": "p", "trace": "t", "label": label, "method": method, "width": 10,
            "height": 20, "rays_per_frame": rays, "ms_per_frame": ms, "metrics": {}, **bands, **comparison,
            **columns}  # fmt: skip


def test_kim2021_counts_the_rays_its_hybrid_renderer_traces_and_shows_the_share_reused():
    """Regular_1 counts every ray; Selective and Sel_Fov all but the primary ray per pixel (10 x 20) that the
    paper rasterises; reuse shows the row's reuse_fraction, "-" without one."""
    rows = [
        _kim_row("full", "full", 500, 5.0),
        _kim_row("Selective", "kim21", 3000, 50.0),
        _kim_row("Sel_Fov", "kim21", 1200, 20.0),
        _kim_row(
            "Sel_Fov reuse",
            "kim21",
            900,
            10.0,
            metrics={"reuse_fraction": 0.375},
            baseline="Sel_Fov",
            speedup_vs_baseline=2.0,
            psnr_fovea_vs_baseline=-0.25,
        ),
    ]
    lines = _lines(kim2021(rows))
    assert [(line[2], line[4], line[5], line[10]) for line in lines] == [
        ("Regular_1", "0", "0", "-"),  # in thousands
        ("Selective", "3", "3", "-"),
        ("Sel_Fov", "1", "1", "-"),
        ("Sel_Fov reuse", "1", "1", "37.5%"),
    ]
    big = [{**r, "rays_per_frame": 1000 * r["rays_per_frame"], "width": 1000, "height": 1000} for r in rows]
    assert [line[5] for line in _lines(kim2021(big))] == ["500", "2,000", "200", "-100"]
    assert lines[3][11:] == ["Sel_Fov", "2.00", "-0.25"]  # reuse against reuse off


def _smith_row(label: str, trace: str, ms: float) -> dict:
    return {"scene": "s", "profile": "p", "trace": trace, "trace_group": "grid", "label": label,
            "method": "rrm" if label != "full" else "full", "options": {"group_w": 3, "group_h": 4},
            "ms_per_frame": ms, "rays_per_frame": 1000, "rays_secondary": 0, "psnr_image": 30.0}  # fmt: skip


def test_smith2013_averages_frame_rates_over_the_fovea_positions_as_section_4_does():
    """Full at 10 and 40 ms (100 and 25 fps), rrm at 5 and 10 ms (200 and 100 fps): mean frame rates 62.5 and
    150 fps, a speed-up of 2.40 (the mean times, 25 and 7.5 ms, would give 3.33)."""
    rows = [_smith_row("full", "a", 10.0), _smith_row("full", "b", 40.0)]
    rows += [_smith_row("rrm", "a", 5.0), _smith_row("rrm", "b", 10.0)]
    [line] = _lines(smith2013(rows))
    assert (line[1], line[3], line[4], line[5], line[8]) == ("grid (2)", "12", "62.5", "150.0", "2.40")


def test_each_table_states_the_date_commit_and_machine_of_its_rows():
    stamp = {"date": "2026-12-03", "commit": "abc1234", "machine": "CPU X, 2 CPUs, Linux x86_64", "score_space": "srgb"}
    rows = [{**_smith_row("full", "a", 10.0), **stamp}, {**_smith_row("rrm", "a", 5.0), **stamp}]
    text = paper_tables(rows, ["smith2013"])
    heading, blank, measured = text.splitlines()[:3]
    assert heading.startswith("### smith2013") and not blank
    assert measured == "Measured 2026-12-03 (UTC) at commit abc1234 on CPU X, 2 CPUs, Linux x86_64."
    later = [{**rows[0], "date": "2026-12-05", "commit": f"abc{k}abc", "machine": f"CPU {k}"} for k in range(5)]
    assert provenance.line([*rows, *later]) == (
        "Measured 2026-12-03 to 2026-12-05 (UTC) at commits abc1234, abc0abc, abc1abc, and 3 more "
        "on machines CPU X, 2 CPUs, Linux x86_64; CPU 0; CPU 1; and 3 more."
    )


def test_the_stamp_names_this_checkouts_commit_and_this_machine(monkeypatch):
    stamp = provenance.stamp()
    assert re.fullmatch(r"[0-9]{4}-[0-9]{2}-[0-9]{2}", stamp["date"])
    assert re.fullmatch(r".+, [0-9]+ CPUs, .+", stamp["machine"]) and stamp["machine"].isprintable()
    root = Path(provenance.__file__).resolve().parents[2]
    head = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0 and (root / ".git").exists():
        assert stamp["commit"].removesuffix("-dirty") == head.stdout.strip()
    else:
        assert stamp["commit"] == "unknown"
    try:  # a checkout that is not hmdrt's own (hmdrt installed inside another repository), or no git at all
        elsewhere = subprocess.CompletedProcess([], 0, stdout="/somewhere/else\nabc1234\n")
        monkeypatch.setattr(provenance, "_git", lambda root, *args: elsewhere)
        provenance.commit.cache_clear()
        assert provenance.commit() == "unknown"

        def missing(root, *args):
            raise FileNotFoundError("git")

        monkeypatch.setattr(provenance, "_git", missing)
        provenance.commit.cache_clear()
        assert provenance.commit() == "unknown"
    finally:
        monkeypatch.undo()
        provenance.commit.cache_clear()


def _latency_row(label: str, ms: float, fovea_db: float, **more) -> dict:
    return {"scene": "whitted", "trace_group": "raccoons", "tracker": "htc-vive-pro-eye", "prediction": "off",
            "label": label, "latency_ms": ms, "psnr_fovea": fovea_db, **more}  # fmt: skip


def test_the_latency_table_gives_the_longest_latency_within_1_db_of_the_methods_own_at_the_least():
    """A method whose foveal PSNR falls by more than 1 dB after 50 ms tolerates 50 ms; one that never falls, at
    least the longest latency run; one that falls at once and recovers, the least (the bound holds from the
    least latency up, without a gap)."""
    falls = [(0, 40.0), (20, 39.5), (50, 39.1), (80, 38.5), (150, 35.0)]
    recovers = [(0, 40.0), (20, 38.0), (50, 40.0), (80, 40.0), (150, 40.0)]
    rows = [_latency_row("kim21", ms, db) for ms, db in falls] + [_latency_row("rrm", ms, db) for ms, db in recovers]
    rows += [_latency_row("full", ms, 30.0) for ms, _ in falls]
    lines = {line[4]: line for line in _lines(latency(rows))}
    assert lines["kim21"][5:] == ["40.00", "39.50", "39.10", "38.50", "35.00", "50 ms"]
    assert lines["rrm"][-1] == "0 ms"
    assert lines["full"][-1] == "at least 150 ms"


def test_the_latency_table_bounds_jod_where_scored_and_keeps_head_trackers_apart():
    """With JOD in the rows a second bound column: the longest latency within 0.5 JOD. Rows that differ in their
    head tracker or pose latency are separate lines, the head named in the tracker cell."""
    jods = [(0, 9.0), (20, 8.8), (50, 8.4), (80, 8.0)]
    rows = [_latency_row("kim21", ms, 40.0, jod=j) for ms, j in jods]
    rows += [_latency_row("kim21", ms, 40.0 - ms / 20, jod=9.0, pose_tracker="htc-vive", pose_latency_ms=20.0)
             for ms, _ in jods]  # fmt: skip
    table = latency(rows)
    assert table.splitlines()[0].endswith("| within 1 dB up to | within 0.5 JOD up to |")
    lines = {line[2]: line for line in _lines(table)}
    assert lines["htc-vive-pro-eye"][-2:] == ["at least 80 ms", "20 ms"]
    assert lines["htc-vive-pro-eye; head htc-vive 20 ms"][-2:] == ["20 ms", "at least 80 ms"]
