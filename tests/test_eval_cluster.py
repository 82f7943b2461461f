"""hmdrt eval on Dask distributed: the same image-derived columns as the serial run, ground truths in row
blocks bit for bit the whole image's, no finished cell lost when a worker is killed, --resume, and one-line errors
for a scheduler that cannot be reached or a missing extra."""

from __future__ import annotations

import json
import os
import signal
import socket
import sys
from pathlib import Path

import numpy as np
import pytest

distributed = pytest.importorskip("distributed")

from hmdrt.cli import main  # noqa: E402
from hmdrt.evaluate.config import load_eval_config  # noqa: E402
from hmdrt.evaluate.groups import group_id, groups  # noqa: E402
from hmdrt.evaluate.partial import PartialResults  # noqa: E402
from hmdrt.evaluate.results import image_columns  # noqa: E402
from hmdrt.evaluate.runner import evaluate  # noqa: E402
from hmdrt.evaluate.truth import truth_rows  # noqa: E402
from hmdrt.optics import get_profile  # noqa: E402
from hmdrt.scene import load_scene  # noqa: E402
from hmdrt.spatial import Pose  # noqa: E402
from hmdrt.trace.integrator import Whitted  # noqa: E402
from hmdrt.views import eye_cameras  # noqa: E402

HEAD = """
scenes = ["whitted"]
resolution = "48x54"
frames = 4
warmup_frames = 1
timing_rounds = 1  # the images are under test here, not the times
truth_spp = 4
{cache}
[[methods]]
name = "full"

[[methods]]
name = "rrm"
options = {{ group_w = 2, group_h = 1 }}
sweep = {{ fovea_deg = [5.0, 20.0] }}

[[traces]]
gaze = "0,0"

[[traces]]
name = "path"
builtin = true
latency_ms = 50.0  # the methods see the gaze as a 120 Hz tracker reported it, 50 ms late
tracker = "fove-0"
"""
MORE = '\n[[traces]]\ngaze = "8,0"\n\n[[traces]]\ngaze = "-8,4"\n'  # two groups more (the head still: one truth)


def _config(folder: Path, cache: str = 'cache_dir = "cache"', groups: int = 2) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "eval.toml"
    path.write_text(HEAD.format(cache=cache) + (MORE if groups == 4 else ""))
    return path


def _rows(out: Path) -> list[dict]:
    return json.loads((out / "results.json").read_text())["rows"]


def _images(rows: list[dict]) -> dict[tuple, dict]:
    return {(r["scene"], r["profile"], r["trace"], r["label"]): image_columns(r) for r in rows}


@pytest.fixture(scope="module")
def client():
    """One LocalCluster of two one-thread worker processes for the module (its start-up costs seconds)."""
    with (
        distributed.LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=":0") as cluster,
        distributed.Client(cluster) as c,
    ):
        yield c


@pytest.fixture(scope="module")
def serial(tmp_path_factory) -> dict[tuple, dict]:
    """The image-derived columns of the four-group config rendered in process, with whole-image truths."""
    config = load_eval_config(_config(tmp_path_factory.mktemp("serial"), groups=4))
    return _images(evaluate(config, progress=False).rows)


def test_row_blocks_of_a_truth_are_bit_for_bit_the_whole_image():
    scene = load_scene("whitted")
    profile = get_profile("sim-cpu").with_resolution_text("48x54", "resolution")
    camera = eye_cameras(profile, Pose.looking([0.1, 1.6, 2.0], 15.0, -5.0), ("left",))["left"]
    with Whitted(scene, threads=2) as tracer:
        whole = truth_rows(tracer, camera, 4, 3, 0, 54)
        blocks = [truth_rows(tracer, camera, 4, 3, r0, r1 - r0) for r0, r1 in ((0, 1), (1, 20), (20, 54))]
    assert whole.dtype == np.float32 and whole.std() > 0
    assert np.array_equal(np.concatenate(blocks), whole)


def test_local_cluster_of_two_gets_the_serial_image_columns(tmp_path, monkeypatch, capsys):
    """Without a cache_dir in the config the truths travel through the scheduler into this machine's cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    path = _config(tmp_path / "cfg", cache="")
    serial = evaluate(load_eval_config(_config(tmp_path / "serial")), progress=False).rows
    out = tmp_path / "out"
    assert main(["eval", str(path), "--out", str(out), "--no-plots", "--cluster", "local:2"]) == 0
    assert "Dask dashboard at http" in capsys.readouterr().err
    rows = _rows(out)
    assert [r["label"] for r in rows] == [r["label"] for r in serial]
    assert _images(rows) == _images(serial) and all(r["psnr_image"] for r in rows)
    gaze = ("latency_ms", "tracker", "gaze_error_p50_deg", "gaze_error_p95_deg", "gaze_outside_fovea")
    assert [[r[k] for k in gaze] for r in rows] == [[r[k] for k in gaze] for r in serial]
    assert {r["gaze_error_p50_deg"] > 1.0 for r in rows} == {False, True}  # the still gaze is seen exactly
    assert all(r["worker"].startswith("tcp://") and r["group_seconds"] > 0 for r in rows)
    assert all(r["worker"] is None for r in serial)
    # the methods' metrics come back (image columns, compared above) and each worker stamps its rows
    assert all(r["metrics"]["fovea_pixels"] > 0 for r in rows if r["method"] == "rrm")
    assert {(r["commit"], r["machine"]) for r in rows} == {(serial[0]["commit"], serial[0]["machine"])}
    truth = json.loads((out / "results.json").read_text())["truth"]
    assert (truth["rendered"], truth["read"]) == (4, 0)  # the head still: one view; the path: three
    assert len(list((tmp_path / "xdg" / "hmdrt" / "truth").glob("*.npy"))) == 4


def test_a_worker_killed_mid_run_loses_no_cell_and_dask_reruns_its_task(client, serial, tmp_path, monkeypatch):
    """When a group has finished while another is running or held, that worker is killed (SIGKILL): Dask renders
    the other group again elsewhere and every cell comes back, with the serial image columns. (When the first group
    finishes, the others may still wait for their truths, so the kill waits for a group in flight.)"""
    path = _config(tmp_path, groups=4)
    killed: dict = {}
    keep = PartialResults.add

    def add(self, gid, result):
        keep(self, gid, result)
        if killed:
            return
        held = {k: ws[0] for k, ws in client.who_has().items() if ws}
        running = {k: w for w, ks in client.processing().items() for k in ks}
        others = {k: w for k, w in {**held, **running}.items() if str(k).startswith("group-") and gid not in str(k)}
        if not others:
            return
        key, address = next(iter(others.items()))
        os.kill(client.run(os.getpid, workers=[address])[address], signal.SIGKILL)
        killed.update(address=address, gid=str(key).split("-")[1])

    monkeypatch.setattr(PartialResults, "add", add)
    out = tmp_path / "out"
    assert main(["eval", str(path), "--out", str(out), "--no-plots", "--cluster", client.scheduler.address]) == 0
    assert killed, "no group was running or held beside a finished one: no worker was killed"
    rows = _rows(out)
    assert len(rows) == 4 * 3 and _images(rows) == serial
    assert len(list((out / "partial").glob("*.npz"))) == 4
    config = load_eval_config(path)
    [lost] = [key.trace.label for key in groups(config) if group_id(config, key) == killed["gid"]]
    assert all(r["worker"] != killed["address"] for r in rows if r["trace"] == lost)  # rendered again elsewhere
    assert len(list((tmp_path / "cache").glob("*.npy"))) == 4  # the workers wrote the shared cache


def test_resume_renders_only_the_groups_not_finished(client, serial, tmp_path):
    path = _config(tmp_path, groups=4)
    out = tmp_path / "out"
    cluster = ["--no-plots", "--cluster", client.scheduler.address]
    assert main(["eval", str(path), "--out", str(out), *cluster]) == 0
    first = {(r["trace"], r["label"]): r for r in _rows(out)}
    files = sorted((out / "partial").glob("*.npz"))
    files[0].unlink()  # never finished
    files[1].write_bytes(b"not a zip")  # cut short: rendered again
    assert main(["eval", str(path), "--resume", str(out), *cluster]) == 0
    rows = _rows(out)
    assert _images(rows) == serial
    again = {(r["trace"], r["label"]) for r in rows if r != first[(r["trace"], r["label"])]}
    assert len({trace for trace, _ in again}) == 2  # worker and group_seconds differ where a group ran again
    assert len({trace for trace, _ in first}) == 4


def test_a_scheduler_that_cannot_be_reached_is_a_one_line_error(tmp_path, capsys):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{s.getsockname()[1]}"  # nobody listens there
    import dask

    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        code = main(["eval", str(_config(tmp_path)), "--out", str(tmp_path / "out"), "--cluster", address])
    err = capsys.readouterr().err
    assert code == 1 and err.startswith(f"hmdrt: error: cannot reach the Dask scheduler at {address}")
    assert err.count("\n") == 1


def test_cluster_without_the_extra_is_one_error_naming_it(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    assert main(["eval", str(_config(tmp_path)), "--out", str(tmp_path / "out"), "--cluster", "local:2"]) == 1
    err = capsys.readouterr().err
    assert "pip install -e '.[cluster]'" in err and err.count("\n") == 1


@pytest.mark.parametrize("spec", ["local:0", "local:", "8786", "http://host:8786"])
def test_bad_cluster_values_are_refused_by_the_parser(tmp_path, spec, capsys):
    with pytest.raises(SystemExit):
        main(["eval", str(_config(tmp_path)), "--out", str(tmp_path / "out"), "--cluster", spec])
    assert "neither local:N" in capsys.readouterr().err
