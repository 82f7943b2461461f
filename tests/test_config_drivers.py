"""A run config's driver URLs: parsed by DriverUrl.parse alone, with the file paths each driver class declares
(replay://PATH, hid://stub?trace=PATH, a test driver's own) taken relative to the config file."""

from __future__ import annotations

from pathlib import Path

import pytest

from hmdrt.compositor.config import load_config
from hmdrt.drivers import REGISTRY, DriverNotFound, DriverUrl, open_driver, register
from hmdrt.drivers.synthetic import SyntheticDriver
from hmdrt.errors import ConfigError


class CalibratedDriver(SyntheticDriver):
    """A driver whose calibration= option names a file."""

    scheme = "calibrated"
    options = {**SyntheticDriver.options, "calibration": (str, "", None, None), "profile": (str, "", None, None)}
    path_options = ("calibration",)


def drivers_of(folder: Path, *urls: str) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "run.toml"
    path.write_text("".join(f'[[drivers]]\nurl = "{url}"\n' for url in urls))
    return [d.url for d in load_config(path).drivers]


def test_paths_a_driver_declares_are_relative_to_the_config_file(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = tmp_path / "my configs"
    replay, hid = drivers_of(folder, "replay://traces/a b.jsonl?speed=2&loop=1", "hid://stub?trace=head.jsonl&seed=3")
    driver = open_driver(replay)
    assert driver.path == folder / "traces" / "a b.jsonl" and driver.opt["speed"] == 2.0 and driver.opt["loop"]
    driver = open_driver(hid)
    assert driver.opt["trace"] == str(folder / "head.jsonl") and driver.opt["seed"] == 3


def test_absolute_paths_and_urls_without_paths_are_left_as_written(tmp_path):
    urls = (
        "replay:///data/a.jsonl?speed=0",
        "hid://stub?trace=/data/head.jsonl",
        "synthetic://?seed=1&rate=250",
        "smi://127.0.0.1:4444?listen=5555",
        "serial://?port=loop://&protocol=razor",
        "replay://",  # no trace: the driver says so when it starts
    )
    assert drivers_of(tmp_path, *urls) == list(urls)


def test_a_registered_driver_s_declared_path_options_are_resolved_and_no_others(tmp_path):
    register("calibrated", f"{__name__}:CalibratedDriver")
    try:
        (url,) = drivers_of(tmp_path, "calibrated://?calibration=cal/eye.json&profile=rift.toml&seed=2")
    finally:
        del REGISTRY["calibrated"]
    options = DriverUrl.parse(url).options
    assert options == {"calibration": str(tmp_path / "cal" / "eye.json"), "profile": "rift.toml", "seed": "2"}


@pytest.mark.parametrize(
    "url, error, message",
    [
        ("bogus://x", DriverNotFound, "no driver for bogus://"),
        ("traces/a.jsonl", ConfigError, "needs a scheme"),
        ("synthetic://?seed", ConfigError, "bad query"),
        ("smi://[::1", ConfigError, "Invalid IPv6 URL"),
    ],
)
def test_a_driver_url_that_does_not_parse_is_an_error_when_the_config_loads(tmp_path, url, error, message):
    with pytest.raises(error, match=message):
        drivers_of(tmp_path, url)


def test_driver_url_location_and_replace_round_trip():
    url = DriverUrl.parse("replay://Traces/a%20b.jsonl?speed=2")
    assert url.location == "Traces/a b.jsonl" and url.host == "traces"
    moved = url.replace("/data/x?#.jsonl")
    assert moved.location == "/data/x?#.jsonl" and moved.options == {"speed": "2"}
    assert url.replace(speed="0").text == "replay://Traces/a%20b.jsonl?speed=0"
    assert url.replace().text == url.text
