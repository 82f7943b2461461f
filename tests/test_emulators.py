"""The emulator registry: each emulator class declares its devices (name, default port, rate, latency) and
registers; make_emulator and `hmdrt emulate` read the declarations and know no device by name."""

from __future__ import annotations

import inspect
import json
import re
from pathlib import Path

import pytest

import hmdrt.drivers.emulators as emulators
from hmdrt.cli import main
from hmdrt.drivers.emulators import EMULATORS, EYE_TRACKERS, REGISTRY, make_emulator, register
from hmdrt.drivers.emulators.base import Emulated, Emulator, EmulatorOptions
from hmdrt.errors import ConfigError

PROTOCOLS_MD = Path(__file__).resolve().parent.parent / "docs" / "protocols.md"


class ToyEmulator(Emulator):
    """A device that serves nothing, declared and registered the way the built-in emulators are."""

    name = "toy"
    emulates = (Emulated("toy", rate_hz=5.0, reached="is a toy in this process"),)

    def __init__(self, rate_hz: float, clock):
        super().__init__(clock)
        self.rate_hz = rate_hz

    @classmethod
    def emulate(cls, device: Emulated, options: EmulatorOptions) -> ToyEmulator:
        return cls(options.rate_for(device), options.clock)

    @property
    def url(self) -> str:
        return f"synthetic://?rate={self.rate_hz:g}"

    def _bind(self) -> None:
        pass

    def _release(self) -> None:
        pass

    def _tick(self, now_ns: int) -> int:
        return now_ns + 10**9

    def _poll(self, timeout_s: float) -> None:
        self._stop.wait(timeout_s)


@pytest.fixture
def toy():
    register(ToyEmulator)
    yield ToyEmulator
    del REGISTRY["toy"]


def test_the_built_in_devices_in_the_order_hmdrt_emulate_lists_them():
    assert list(EMULATORS) == ["smi", "fove", "pupil", "lsl", "razor", "hatire"]
    assert EYE_TRACKERS == ("smi", "fove", "pupil", "lsl")
    for name, entry in REGISTRY.items():
        assert entry.device.name == name and entry.device in entry.cls.emulates


@pytest.mark.parametrize("name", list(REGISTRY))
def test_make_emulator_builds_each_device_with_the_defaults_its_class_declares(name):
    device = REGISTRY[name].device
    emulator = make_emulator(name)
    assert isinstance(emulator, REGISTRY[name].cls) and not emulator.running
    assert getattr(emulator, "port", None) == device.port
    rate_hz = emulator.feed.rate_hz if device.latency_ms is not None else emulator.rate_hz
    assert rate_hz == device.rate_hz
    if device.latency_ms is not None:
        assert emulator.feed.latency_ns == round(device.latency_ms * 1e6)
    faster = make_emulator(name, rate_hz=2 * device.rate_hz)
    assert (faster.feed.rate_hz if device.latency_ms is not None else faster.rate_hz) == 2 * device.rate_hz


def test_the_registry_module_names_no_device():
    """What differs between devices is in their declarations, not in branches of the registry."""
    source = inspect.getsource(emulators)
    assert not [name for name in REGISTRY if re.search(rf"[\"']{name}[\"']", source)]


@pytest.mark.parametrize(
    "device, options, message",
    [
        ("razor", {"trace": "x.jsonl"}, "^the razor emulator is a head tracker on a pseudo-terminal; it takes no"),
        ("hatire", {"port": 1, "latency_ms": 2.0}, "hatire emulator is a head tracker .* takes no --port"),
        ("lsl", {"port": 0}, "the lsl emulator is found by LSL's discovery, not at a port; it takes no --port"),
        ("smi", {"port": 70000}, r"--port must be within 0 and 65535 \(0: any free port\), got 70000"),
        ("fove", {"offset_deg": 50.0}, "--offset must be within -45 and 45, got 50.0"),
        ("pupil", {"noise_deg": -1.0}, "--noise must be within 0 and 10, got -1.0"),
        ("smi", {"latency_ms": 2000.0}, "--latency must be within 0 and 1000, got 2000.0"),
        ("nope", {}, "no emulator 'nope'; emulators: smi, fove, pupil, lsl, razor, hatire"),
    ],
)
def test_options_a_device_does_not_take_or_out_of_range_are_one_error(device, options, message):
    with pytest.raises(ConfigError, match=message):
        make_emulator(device, **options)


def test_a_registered_class_is_an_emulator_like_the_built_in_ones(toy):
    assert "toy" in EMULATORS and "toy" not in EYE_TRACKERS
    with make_emulator("toy", rate_hz=8.0) as emulator:
        assert isinstance(emulator, ToyEmulator) and emulator.running and emulator.rate_hz == 8.0
    with pytest.raises(ConfigError, match="the toy emulator is a toy in this process; it takes no --port"):
        make_emulator("toy", port=0)


def test_hmdrt_emulate_offers_a_registered_device(toy, capsys, own_signals):
    assert main(["emulate", "toy", "--duration", "0.05"]) == 0
    assert capsys.readouterr().out == "toy emulator: connect with: hmdrt driver 'synthetic://?rate=5'\n"


def test_a_class_without_a_declared_device_does_not_register():
    class Silent(ToyEmulator):
        emulates = ()

    with pytest.raises(TypeError, match="Silent declares no device"):
        register(Silent)


def test_the_defaults_table_in_the_protocols_doc_matches_the_declarations():
    text = PROTOCOLS_MD.read_text()
    rows = re.findall(r"^\| `(\w+)` \| [^|]+ \| ([^|]+) \| ([^|]+) \| ([^|]+) \|$", text, re.MULTILINE)
    assert sorted(name for name, *_ in rows) == sorted(REGISTRY)
    for name, port, rate, latency in rows:
        device = REGISTRY[name].device
        assert re.match(r"\d+|-", port.strip()).group() == (str(device.port) if device.port is not None else "-")
        assert float(re.match(r"[\d.]+", rate.strip()).group()) == device.rate_hz, name
        declared = "-" if device.latency_ms is None else f"{device.latency_ms:g} ms"
        assert latency.strip() == declared, name


@pytest.mark.usefixtures("own_signals")
def test_the_emulated_tracker_config_runs_a_compositor_on_an_emulators_gaze(tmp_path, capsys):
    """configs/emulated_tracker.toml, as the README's tour runs it beside `hmdrt emulate smi`: the compositor's
    SMI driver receives the emulator's gaze over UDP and the run reports it (here on a free port, not 4444)."""
    shipped = Path(__file__).resolve().parents[1] / "configs" / "emulated_tracker.toml"
    with make_emulator("smi", port=0, seed=1) as emulator:
        config = tmp_path / "emulated_tracker.toml"
        config.write_text(shipped.read_text().replace("smi://127.0.0.1:4444?listen=0", emulator.url))
        report = tmp_path / "report.json"
        assert main(["run", str(config), "--duration", "2", "--report", str(report)]) == 0
    gaze = json.loads(report.read_text())["latency_ms"]["gaze_to_photon"]
    assert gaze["p50"] is not None  # frames were shown with the emulator's gaze
    assert "gaze-to-photon p99 n/a" not in capsys.readouterr().out
