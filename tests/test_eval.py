"""hmdrt eval: the command end to end, its configs, warm-up, paper tables and plots (scores: test_eval_scores.py)."""

from __future__ import annotations

import csv
import json
import statistics
import sys
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest

from hmdrt.cli import main
from hmdrt.errors import ConfigError
from hmdrt.evaluate import results
from hmdrt.evaluate.config import MethodSweep, load_eval_config
from hmdrt.evaluate.quality import BANDS
from hmdrt.foveation import MethodChoice
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose
from hmdrt.trace.integrator import Whitted
from hmdrt.views import FrameInput
from tests.helpers import DATA

RNG = np.random.default_rng(7)


EVAL = """
scenes = ["whitted"]
resolution = "48x54"
frames = 4
warmup_frames = 1
truth_spp = 4
cache_dir = "cache"

[[traces]]
gaze = "0,0"

[[traces]]
name = "path"
builtin = true

[[methods]]
name = "full"

[[methods]]
name = "rrm"
options = { group_w = 1, group_h = 1 }
sweep = { fovea_deg = [5.0, 20.0] }
"""


def test_hmdrt_eval_writes_one_row_per_cell_with_band_scores_plots_and_a_summary(tmp_path, capsys):
    config = tmp_path / "eval.toml"
    config.write_text(EVAL)
    out = tmp_path / "out"
    assert main(["eval", str(config), "--out", str(out)]) == 0
    stdout = capsys.readouterr().out
    with open(out / "results.csv") as f:
        rows = list(csv.DictReader(f))
    result = json.loads((out / "results.json").read_text())
    assert len(rows) == len(result["rows"]) == 2 * 3  # two traces x (full + two rrm settings)
    assert {r["params"] for r in rows} == {
        "full",
        "rrm?fovea_deg=5.0&group_w=1&group_h=1",  # as MethodChoice writes it: the fields in their order
        "rrm?fovea_deg=20.0&group_w=1&group_h=1",
    }
    assert result["score_space"] == "srgb" and "PSNR, SSIM and flicker of display-encoded (sRGB) images" in stdout
    for r in result["rows"]:
        assert r["frames"] == 3 and r["ms_per_frame"] > 0 and r["width"] == 48 and r["height"] == 54
        assert r["score_space"] == "srgb" and r["baseline"] == "full"
        assert all(f"{k}_{b}" in r for k in ("psnr", "ssim", "flicker") for b in (*BANDS, "image"))
        assert r["psnr_image"] is not None and 0 < r["psnr_image"] < 100
    full = [r for r in result["rows"] if r["method"] == "full"]
    assert all(r["speedup_vs_full"] == 1.0 and r["sample_fraction"] == 1.0 for r in full)
    # rrm's per-frame metrics, averaged: its sample fraction and its fovea's pixels; full reports none
    assert [set(r["metrics"]) for r in result["rows"]] == 2 * [set(), *2 * [{"sample_fraction", "fovea_pixels"}]]
    assert all(r["metrics"]["sample_fraction"] == r["sample_fraction"] for r in result["rows"] if r["metrics"])
    assert {r["metric_fovea_pixels"] != "" for r in rows} == {True, False}  # a CSV column, empty for full
    # rrm with N = 1 refreshes every pixel each frame: the image is full's, and a smaller fovea is no cheaper
    for r in result["rows"]:
        twin = next(f for f in full if f["trace"] == r["trace"])
        assert r["psnr_image"] == pytest.approx(twin["psnr_image"], abs=1e-6)
    assert result["truth"]["rendered"] == 1 + 3  # still head: one view; the head path: three scored views
    assert [(s["trace"], s["baseline"]) for s in result["summary"]] == [("gaze 0,0", "full"), ("path", "full")]
    assert sorted(p.name.split("_")[0] for p in out.glob("*.png")) == [
        "band",
        "band",
        "crops",
        "crops",
        "error",
        "error",
    ]
    assert "target: foveal PSNR at least full's " in stdout  # each group's summary line, with its verdict

    assert main(["eval", str(config), "--out", str(out), "--no-plots", "--frames", "3"]) == 0
    again = json.loads((out / "results.json").read_text())
    assert again["truth"] == {**result["truth"], "rendered": 0, "read": 2 * 2}  # the cache answers


@pytest.mark.parametrize(
    "text, message",
    [
        ("frames = 2\nwarmup_frames = 2\n", "warmup_frames (2) must be fewer than frames (2)"),
        ('[[methods]]\nname = "nosuch"\n', "unknown method 'nosuch'"),
        ('[[methods]]\nname = "rrm"\nsweep = { group_w = [0] }\n', "method 'rrm'"),
        ('[[traces]]\ngaze = "0,0"\nbuiltin = true\n', "exactly one of gaze, path or builtin"),
        ('[[traces]]\ngaze = "95,0"\n', "within +-90 degrees"),
        ("scenes = []\n", "at least one entry"),
        ("nonsense = 1\n", "unknown field `nonsense`"),
        ('score_space = "log"\n', "Invalid enum value 'log' - at `$.score_space`"),
        (
            '[[methods]]\nname = "full"\ncompare_to = "nosuch"\n',
            "compare_to 'nosuch' names no cell (labels there: 'full')",
        ),
        (
            '[[methods]]\nname = "full"\nlabel = "a"\n[[methods]]\nname = "rrm"\nlabel = "a"\n'
            '[[methods]]\nname = "rrm"\noptions = { block = 2 }\ncompare_to = "a"\n',
            "compare_to 'a' names 2 cells on scene 'whitted'",
        ),
        (
            'scenes = ["whitted", "tunnel_maps"]\n[[methods]]\nname = "full"\nscenes = ["whitted"]\n'
            '[[methods]]\nname = "rrm"\ncompare_to = "full"\n',
            "on scene 'tunnel_maps'",
        ),
        ('[[methods]]\nname = "rrm"\ncompare_to = "a\\nb"\n', "compare_to 'a\\nb' names no cell"),
    ],
)
def test_bad_eval_configs_are_one_line_errors(tmp_path, text, message):
    config = tmp_path / "bad.toml"
    config.write_text(text)
    with pytest.raises(ConfigError, match=None) as err:
        load_eval_config(config)
    assert message in str(err.value) and "\n" not in str(err.value)


def test_hmdrt_eval_into_an_unwritable_folder_fails_before_rendering(tmp_path, capsys):
    config = tmp_path / "eval.toml"
    config.write_text(EVAL)
    (tmp_path / "file").write_text("")
    assert main(["eval", str(config), "--out", str(tmp_path / "file" / "out")]) == 1
    err = capsys.readouterr().err
    assert err.startswith("hmdrt: error: cannot write") and err.count("\n") == 1
    assert not (tmp_path / "cache").exists()  # nothing was rendered


def test_eval_config_paths_are_relative_to_the_file(tmp_path):
    (tmp_path / "sub").mkdir()
    config = tmp_path / "sub" / "e.toml"
    config.write_text('cache_dir = "c"\n[[traces]]\npath = "t.jsonl"\n')
    loaded = load_eval_config(config)
    assert (
        Path(loaded.cache_dir) == tmp_path / "sub" / "c" and Path(loaded.traces[0].path) == tmp_path / "sub" / "t.jsonl"
    )


def table_lines(markdown: str, title: str) -> list[list[str]]:
    """The body rows of the Markdown table under the heading that starts with `title`."""
    section = markdown.split(f"### {title}")[1].split("###")[0]
    lines = [line for line in section.splitlines() if line.startswith("|")][2:]  # past the header and its rule
    return [[c.strip() for c in line.strip("|").split("|")] for line in lines]


def test_paper_tables_are_filled_from_the_labelled_cells_of_each_scene(tmp_path):
    config = tmp_path / "tables.toml"
    text = (DATA / "eval_tables.toml").read_text()
    config.write_text(text.replace('label = "Sel_Fov"\n', 'label = "Sel_Fov"\ncompare_to = "Selective"\n'))
    assert main(["eval", str(config), "--out", str(tmp_path / "out"), "--no-plots"]) == 0
    rows = json.loads((tmp_path / "out" / "results.json").read_text())["rows"]
    assert {r["scene"] for r in rows if r["label"] == "weier18"} == {"whitted?max_depth=0"}  # scenes = [...]
    # ahead: whitted full, weier16, Regular_36, Selective, Sel_Fov, Sel_Fov reuse, rrm; the other full, rrm,
    # 2 x weier18; on each of the two grid traces (traces = [...]): full, rrm and rrm N=4 on both scenes
    assert len(rows) == 7 + 4 + 2 * 2 * 3
    markdown = (tmp_path / "out" / "tables.md").read_text()
    by = {(r["scene"], r["trace"], r["label"]): r for r in rows}
    # under each heading: the date, commit and machine of the rows (one run: one of each)
    [measured] = {line for line in markdown.splitlines() if line.startswith("Measured ")}
    assert markdown.count(measured) == markdown.count("### ") == 4
    assert measured == f"Measured {rows[0]['date']} (UTC) at commit {rows[0]['commit']} on {rows[0]['machine']}."

    [weier16] = table_lines(markdown, "weier2016")
    full, ours = by["whitted", "ahead", "full"], by["whitted", "ahead", "weier16"]
    assert weier16[:2] == ["whitted", "ahead"] and float(weier16[-1]) == pytest.approx(
        full["ms_per_frame"] / ours["ms_per_frame"], abs=0.01
    )
    assert weier16[6] == f"{ours['stages_ms']['trace']:.2f}"  # the trace stage's mean ms

    kim = table_lines(markdown, "kim2021")
    assert [line[2] for line in kim] == ["Regular_36", "Regular_1", "Selective", "Sel_Fov", "Sel_Fov reuse"]
    assert kim[1][3] == f"{full['ms_per_frame']:.1f}"  # Regular_1 is full's cell
    assert "regular 36 spp, and pixels reused (PSNR of display-encoded" in markdown
    assert [line[11] for line in kim] == ["Regular_1", "Regular_1", "Regular_1", "Selective", "Sel_Fov"]  # compare_to
    selective, sel_fov = by["whitted", "ahead", "Selective"], by["whitted", "ahead", "Sel_Fov"]
    reuse = by["whitted", "ahead", "Sel_Fov reuse"]
    assert kim[3][12] == f"{sel_fov['speedup_vs_baseline']:.2f}"
    speedup = selective["ms_per_frame"] / sel_fov["ms_per_frame"]
    assert sel_fov["speedup_vs_baseline"] == pytest.approx(speedup, abs=5e-4)  # kept to 3 decimals
    assert float(kim[3][13]) == pytest.approx(sel_fov["psnr_fovea"] - selective["psnr_fovea"], abs=0.01)
    assert (kim[1][12], kim[1][13]) == ("1.00", "+0.00")  # full against itself
    # reuse against reuse off: its speed-up and what it costs in the fovea
    assert float(kim[4][12]) == pytest.approx(sel_fov["ms_per_frame"] / reuse["ms_per_frame"], rel=0.01, abs=0.01)
    assert float(kim[4][13]) == pytest.approx(reuse["psnr_fovea"] - sel_fov["psnr_fovea"], abs=0.01)
    fraction = reuse["metrics"].get("reuse_fraction")
    assert kim[4][10] == ("-" if fraction is None else f"{100 * fraction:.1f}%")
    assert by["whitted", "ahead", "Regular_36"]["rays_primary"] == 3 * 48 * 54
    # rays as kim2021 counts them: every ray of a plain ray tracer, the hybrid's without the rasterised presample
    assert [int(line[5].replace(",", "")) for line in kim[:2]] == [int(line[4].replace(",", "")) for line in kim[:2]]
    assert sel_fov["rays_primary"] > 48 * 54
    assert int(kim[3][5].replace(",", "")) == round((sel_fov["rays_per_frame"] - 48 * 54) / 1e3)

    smith = table_lines(markdown, "smith2013")
    assert sorted(line[2] for line in smith if line[1] == "ahead (1)") == ["no", "yes"]  # with and without
    grid = [line for line in smith if line[0] == "whitted" and line[1] == "grid (2)"]
    assert [line[3] for line in grid] == ["2", "4"]  # each cell's N
    for line, label in zip(grid, ("rrm", "rrm N=4"), strict=True):  # frame rates averaged over the fovea positions
        f = statistics.fmean(1e3 / by["whitted", t, "full"]["ms_per_frame"] for t in ("left", "right"))
        r = statistics.fmean(1e3 / by["whitted", t, label]["ms_per_frame"] for t in ("left", "right"))
        assert (line[4], line[5], line[8]) == (f"{f:.1f}", f"{r:.1f}", f"{r / f:.2f}")

    foveated, every = table_lines(markdown, "weier2018")
    assert (foveated[2], every[2]) == ("foveated", "full")
    assert int(every[-1].replace(",", "")) == 48 * 54 > int(foveated[-1].replace(",", ""))


def test_methods_run_on_the_traces_they_name_and_unknown_names_are_refused(tmp_path):
    config = tmp_path / "e.toml"
    config.write_text(EVAL + '\n[[traces]]\nname = "a"\ngaze = "5,0"\ngroup = "g"\n')
    load = load_eval_config(config)
    traces = {t.label: t for t in load.traces}
    assert [t.group_label for t in load.traces][-1] == "g"
    assert all(load.cells("whitted", t) == load.cells("whitted") for t in load.traces)  # traces = []: all
    config.write_text(config.read_text().replace('name = "rrm"', 'name = "rrm"\ntraces = ["g"]', 1))
    load = load_eval_config(config)
    assert [c.label for c in load.cells("whitted", traces["a"])] == [c.label for c in load.cells("whitted")]
    assert all(c.choice.name != "rrm" for t in load.traces if t.label != "a" for c in load.cells("whitted", t))
    config.write_text(config.read_text().replace('traces = ["g"]', 'traces = ["nowhere"]'))
    with pytest.raises(ConfigError, match="names traces not in traces: nowhere"):
        load_eval_config(config)


@pytest.fixture
def render_calls(monkeypatch) -> dict[str, int]:
    """Renders per method choice (str) of the methods made while the test runs."""
    calls: dict[str, int] = {}
    real = MethodChoice.make

    def counting(choice, tracer):
        method = real(choice, tracer)
        render = method.render

        def counted(request, stats):
            calls[str(choice)] = calls.get(str(choice), 0) + 1
            return render(request, stats)

        method.render = counted
        return method

    monkeypatch.setattr(MethodChoice, "make", counting)
    return calls


def test_full_and_regular_skip_the_warm_up_frames(tmp_path, render_calls):
    config = tmp_path / "e.toml"
    config.write_text(EVAL.replace("frames = 4\nwarmup_frames = 1", "frames = 5\nwarmup_frames = 3"))
    load = load_eval_config(config)
    from hmdrt.evaluate import runner

    runner.evaluate(load, progress=False)
    assert render_calls["full"] == 3 * 2 * 2  # three timing rounds x two traces x the two timed frames
    assert render_calls["rrm?fovea_deg=5.0&group_w=1&group_h=1"] == 3 * 2 * 5


def test_timing_rounds_measure_each_cell_afresh_and_a_noisy_speed_up_is_marked_and_left_out(tmp_path, monkeypatch):
    """Each timing round renders the warm-up and the timed frames from a fresh method; ms_per_frame is the median
    of the rounds' means, so one slow round moves it little, but the speed-up's spread over the rounds shows it:
    above 15% the cell is marked noisy, and the summary leaves it out of its best cells and says so."""
    from hmdrt.evaluate import runner

    made: list[str] = []
    real = MethodChoice.make
    slow_round = 2  # the third round of an rrm cell

    def making(choice, tracer):
        method = real(choice, tracer)
        made.append(str(choice))
        if str(choice) == "rrm?fovea_deg=20.0&group_w=1&group_h=1" and made.count(str(choice)) == slow_round + 1:
            render = method.render

            def slow(request, stats):
                time.sleep(0.2)
                return render(request, stats)

            method.render = slow
        return method

    monkeypatch.setattr(MethodChoice, "make", making)
    config = tmp_path / "e.toml"
    config.write_text(EVAL.replace('[[traces]]\nname = "path"\nbuiltin = true\n', ""))
    evaluation = runner.evaluate(load_eval_config(config), progress=False)
    assert made.count("full") == 3  # the scored round's method, then two fresh ones
    rows = {r["label"]: r for r in evaluation.rows}
    slowed, steady = rows["rrm?fovea_deg=20.0&group_w=1&group_h=1"], rows["full"]
    assert slowed["timing_rounds"] == 3 and slowed["speedup_spread"] > 0.5 and slowed["timing_noisy"]
    assert slowed["ms_per_frame"] < 200.0  # the median round: the slow one moved the speed-up's spread, not it
    assert steady["speedup_spread"] == 0.0 and not steady["timing_noisy"]  # full against itself
    assert all(r["cpu_ms_per_frame"] > 0 for r in evaluation.rows)
    [summary] = evaluation.summary
    assert "rrm?fovea_deg=20.0&group_w=1&group_h=1" in summary["noisy"]
    assert summary["best"] != "rrm?fovea_deg=20.0&group_w=1&group_h=1"
    [line] = [line for line in results.table(evaluation).splitlines() if "noisy" in line and " at sim-cpu, " in line]
    assert "rrm?fovea_deg=20.0&group_w=1&group_h=1" in line.rpartition(": ")[2]


@pytest.mark.parametrize("path", sorted((DATA.parents[1] / "configs" / "eval").glob("*.toml")), ids=lambda p: p.name)
def test_every_shipped_eval_config_loads(path):
    """Every method spec, baseline and trace name of the shipped eval configs is valid, and traces exist."""
    config = load_eval_config(path)
    assert all(Path(t.path).is_file() for t in config.traces if t.path)
    assert all(config.cells(scene) for scene in config.scenes)


def test_a_longer_warm_up_holds_the_first_frame_so_every_group_scores_the_same_frames(tmp_path):
    """A method that needs more history than warmup_frames warms up before the trace starts: the scored frames,
    and so the truths, are those of a group without it (all read from the cache)."""
    config = tmp_path / "e.toml"
    config.write_text(EVAL.replace('[[traces]]\ngaze = "0,0"\n\n', ""))  # the head path only
    first = load_eval_config(config)
    full_only = msgspec.structs.replace(first, methods=first.methods[:1])
    from hmdrt.evaluate import runner

    alone = runner.evaluate(full_only, progress=False)
    longer = msgspec.structs.replace(
        first, methods=[*first.methods[:1], MethodSweep("rrm", options={"group_w": 2, "group_h": 3})]
    )
    both = runner.evaluate(longer, progress=False)
    assert (alone.truths_rendered, both.truths_rendered, both.truths_read) == (3, 0, 3)
    assert [r["warmup_frames"] for r in both.rows] == [0, 6]  # rrm's N = 6 > warmup_frames = 1
    assert both.rows[0]["psnr_image"] == alone.rows[0]["psnr_image"]
    inputs = [FrameInput(k, 7 * k, Pose.looking([0, 1, 0], 10.0 * k), {}) for k in range(3)]
    held = runner.held_start(inputs, 2, 5)
    assert [(i.frame, i.t_ns) for i in held] == [(k, 5 * k) for k in range(5)]
    assert [i.pose for i in held] == [inputs[0].pose] * 3 + [inputs[1].pose, inputs[2].pose]


def test_jod_without_the_eval_extra_is_a_one_line_error(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "pyfvvdp", None)  # as if not installed: importing it raises ImportError
    config = tmp_path / "e.toml"
    config.write_text("jod = true\n")
    with pytest.raises(ConfigError, match=r"jod = true needs the eval extra \(pip install -e '\.\[eval\]'\)"):
        load_eval_config(config)


def test_jod_scores_sequences_in_video_mode_when_the_eval_extra_is_installed(tmp_path):
    """FovVideoVDP's video mode: a sequence equal to its truth scores 10; noise that changes every frame scores
    below the same amount of noise held still (a temporal artefact that frame-by-frame scoring cannot see)."""
    pytest.importorskip("pyfvvdp")
    from hmdrt.evaluate.perceptual import JodScorer, encode

    profile = get_profile("sim-cpu").with_resolution_text("64x72")
    scorer = JodScorer(profile, "left")
    truth = [encode(np.full((72, 64, 3), 0.2, np.float32))] * 8
    noise = RNG.normal(0, 0.04, (8, 72, 64, 3)).astype(np.float32)
    steady = [encode(np.clip(0.2 + noise[0], 0, 1))] * 8
    flicker = [encode(np.clip(0.2 + n, 0, 1)) for n in noise]
    gazes = [(32.0, 36.0)] * 8
    assert scorer.score(truth, truth, gazes) == pytest.approx(10.0, abs=1e-3)
    assert 0 < scorer.score(flicker, truth, gazes) < scorer.score(steady, truth, gazes) < 10
    config = tmp_path / "e.toml"
    config.write_text(EVAL.replace("frames = 4", "jod = true\nframes = 3"))
    assert main(["eval", str(config), "--out", str(tmp_path / "out"), "--no-plots"]) == 0
    rows = json.loads((tmp_path / "out" / "results.json").read_text())["rows"]
    assert all(0 < r["jod"] <= 10 for r in rows)


def test_a_sweep_of_more_than_max_cells_is_refused_before_any_cell_is_built(tmp_path):
    config = tmp_path / "big.toml"
    values = ", ".join(str(v) for v in range(100))
    config.write_text(
        f'[[methods]]\nname = "rrm"\nsweep = {{ fovea_deg = [{values}], group_w = [{values}], block = [1, 2] }}\n'
    )
    started = time.monotonic()
    with pytest.raises(ConfigError, match="its sweep makes 20000 cells, more than 10000"):
        load_eval_config(config)
    assert time.monotonic() - started < 5


WARMUP = """
scenes = ["whitted"]
resolution = "48x54"
frames = 3
warmup_frames = 1
timing_rounds = 1  # the warm-up is under test here, not the times
truth_spp = 2
cache_dir = "cache"
score_space = "linear"

[[methods]]
name = "full"

[[methods]]
name = "rrm"
label = "rrm"
options = { group_w = 2, group_h = 2 }

[[methods]]
name = "rrm"
label = "rrm small"
options = { fovea_deg = 5.0, group_w = 2, group_h = 2 }
compare_to = "rrm"
"""


def test_each_method_warms_up_for_the_history_it_declares_and_is_compared_with_its_baseline(
    tmp_path, render_calls, capsys
):
    config = tmp_path / "e.toml"
    config.write_text(WARMUP)
    assert main(["eval", str(config), "--out", str(tmp_path / "out"), "--no-plots"]) == 0
    stdout = capsys.readouterr().out
    result = json.loads((tmp_path / "out" / "results.json").read_text())
    full, rrm, small = result["rows"]
    # rrm's N = 2 x 2 frames refresh its whole buffer: the warm-up grows from 1 to 4 frames, full skips it
    assert (full["warmup_frames"], rrm["warmup_frames"], small["warmup_frames"]) == (0, 4, 4)
    cells = ("full", "rrm?group_w=2&group_h=2", "rrm?fovea_deg=5.0&group_w=2&group_h=2")
    assert [render_calls[c] for c in cells] == [2, 4 + 2, 4 + 2]  # the truth's regular renders apart
    assert all(r["frames"] == 2 for r in result["rows"])
    assert rrm["psnr_image"] == pytest.approx(full["psnr_image"], abs=1e-6)  # no pixel left black
    assert small["baseline"] == "rrm" and rrm["baseline"] == "full"
    assert small["speedup_vs_baseline"] == pytest.approx(rrm["ms_per_frame"] / small["ms_per_frame"], rel=1e-2)
    assert small["psnr_fovea_vs_baseline"] == pytest.approx(small["psnr_fovea"] - rrm["psnr_fovea"], abs=1e-4)
    assert [s["baseline"] for s in result["summary"]] == ["full", "rrm"]
    assert result["score_space"] == "linear" and all(r["score_space"] == "linear" for r in result["rows"])
    assert "foveal PSNR at least rrm's" in stdout  # the summary against its baseline, rrm
    assert "of linear radiance images" in stdout


def test_methods_declare_the_history_they_need():
    scene = load_scene("whitted")
    with Whitted(scene) as tracer:
        assert MethodChoice.parse("full").make(tracer).warmup_frames == 0
        assert MethodChoice.parse("regular").make(tracer).warmup_frames == 0
        rrm = MethodChoice.parse("rrm").make(tracer)
        assert rrm.warmup_frames == 12  # smith2013's N = 3 x 4
        rrm.set_params(MethodChoice.parse("rrm?group_w=5&group_h=2").params)
        assert rrm.warmup_frames == 10


def _cluster_rows(labels: list[str], ms: list[float]) -> list[dict]:
    """Rows of one group whose cells lie close together, as full and weier16 small and large did in one measured run."""
    group = {"scene": "s", "profile": "p", "trace": "t", "score_space": "srgb"}
    return [
        {
            **group,
            "label": label,
            "method": label.partition("?")[0],
            "ms_per_frame": t,
            "psnr_fovea": 30.0 + 0.01 * i,
            "pareto": i % 2 == 0,
        }  # fmt: skip
        for i, (label, t) in enumerate(zip(labels, ms, strict=True))
    ]


@pytest.mark.parametrize(
    "ms",
    [
        [3.0, 3.02, 3.04, 3.06, 1.2, 7.9],  # a decade apart at most: minor ticks labelled, formerly 3x10^0
        [0.4, 0.41, 0.42, 2500.0, 2510.0, 40.0],  # four decades
        [3.0, 3.0, 3.0, 3.0, 3.0, 3.0],  # all at one time
    ],
)
def test_error_vs_time_labels_never_overlap_and_ticks_are_plain_numbers(ms):
    from hmdrt.evaluate.plots import error_vs_time_figure, plt

    labels = ["full", "weier16?frc=small", "weier16?frc=large", "rrm?fovea_deg=5.0", "kim21?n_f=4", "Sel_Fov"]
    fig = error_vs_time_figure(_cluster_rows(labels, ms), "s at p, t")
    fig.tight_layout()
    fig.canvas.draw()
    [ax] = fig.axes
    renderer = fig.canvas.get_renderer()
    texts = ax.get_legend().get_texts()
    assert [t.get_text() for t in texts][: len(labels)] == labels
    boxes = [t.get_window_extent(renderer) for t in texts]
    assert not any(a.overlaps(b) for i, a in enumerate(boxes) for b in boxes[i + 1 :])
    assert not ax.get_legend().get_window_extent(renderer).overlaps(ax.get_window_extent(renderer))  # beside the axes
    assert fig.bbox.contains(*ax.get_legend().get_window_extent(renderer).p1)  # and inside the figure
    ticks = [t.get_text() for t in ax.get_xticklabels(which="both") if t.get_text()]
    assert ticks and all(float(t) > 0 for t in ticks)  # plain numbers: no 3x10^0, no mathtext
    plt.close(fig)
