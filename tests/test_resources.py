"""The default run config and its trace as installed with the package (hmdrt/files/resources.py)."""

from __future__ import annotations

from pathlib import Path

from hmdrt.compositor.config import load_config
from hmdrt.drivers.base import DriverUrl
from hmdrt.files.resources import INSTALLED, run_config

CONFIGS = Path(__file__).resolve().parent.parent / "configs"


def test_the_readme_config_runs_from_the_package_where_no_such_file_is_here(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    installed = run_config("configs/default.toml")
    assert installed == INSTALLED / "default.toml"
    assert installed.read_bytes() == (CONFIGS / "default.toml").read_bytes()
    trace = Path(DriverUrl.parse(load_config(installed).drivers[0].url).location)
    assert trace.is_file() and trace.read_bytes() == (CONFIGS / "traces" / "synthetic_250hz.jsonl.gz").read_bytes()


def test_a_file_that_is_here_or_not_shipped_is_left_as_given(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "default.toml").write_text('scene = "whitted"\n')
    assert run_config("configs/default.toml") == Path("configs/default.toml")
    for given in ("configs/nothing.toml", "default.toml", str(tmp_path / "missing" / "configs" / "default.toml")):
        assert run_config(given) == Path(given)
