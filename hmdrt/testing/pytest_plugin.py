"""pytest fixtures for latency-budget tests of the hmdrt compositor (the `pytest11` entry point "hmdrt").

A test asks for a config (hmdrt_config), a compositor on private ipc:// sockets (hmdrt_compositor), a whole run's
report (hmdrt_run), or an emulated eye tracker to feed one (hmdrt_emulator); docs/testing.md has an example.

Nothing heavy is imported here, so pytest runs that use none of these fixtures do not pay for the compositor:
it is imported when a fixture first needs it.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

from hmdrt.telemetry.view import Report
from hmdrt.testing.config import TRACE, write_config

if TYPE_CHECKING:
    import zmq

    from hmdrt.drivers.emulators.base import Emulator
    from hmdrt.testing.runs import Recording


@pytest.fixture
def hmdrt_runtime_dir(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A fresh XDG_RUNTIME_DIR for the test and its subprocesses, so that the compositors' default sockets
    (hmdrt.bus.local) meet neither a real compositor's nor each other's; short, as a Unix socket's path must be."""
    with tempfile.TemporaryDirectory(prefix="hmdrt-xdg-") as folder:
        monkeypatch.setenv("XDG_RUNTIME_DIR", folder)
        yield Path(folder)


@pytest.fixture
def hmdrt_context() -> Iterator[zmq.Context]:
    """A ZeroMQ context of the test's own (room for its own ZAP handler), destroyed with linger 0."""
    import zmq

    ctx = zmq.Context()
    yield ctx
    ctx.destroy(linger=0)


@pytest.fixture
def hmdrt_config(tmp_path: Path) -> Callable[..., Path]:
    """hmdrt_config(method="rrm", eyes="both", trace=TRACE, name="run.toml", **sections): a run config written in
    the test's tmp_path (hmdrt.testing.write_config: 64x72 per eye on sim-cpu at 30 Hz, private ipc:// sockets, the
    trace replayed in a loop)."""

    def make(
        method: str | dict = "rrm",
        eyes: str = "both",
        trace: str | Path = TRACE,
        name: str = "run.toml",
        **sections: dict | list,
    ) -> Path:
        return write_config(tmp_path / name, method, eyes, trace, **sections)

    return make


@pytest.fixture
def hmdrt_compositor(hmdrt_context: zmq.Context, hmdrt_runtime_dir: Path) -> Iterator[Callable[..., Recording]]:
    """hmdrt_compositor(config, **run): a started compositor of the config file (a Recording: it keeps every frame
    record and image it shows), `run` overriding [run] keys (frames, virtual_time, seed, duration_s); run it with
    hmdrt.testing.run_bounded or Background. Closed when the test ends."""
    from hmdrt.testing.runs import Recording

    started: list[Recording] = []

    def start(config: Path, **run: Any) -> Recording:
        from hmdrt.compositor.config import load_config

        comp = Recording(load_config(config, **run), context=hmdrt_context)
        started.append(comp)
        return comp

    yield start
    for comp in reversed(started):
        comp.close()


@pytest.fixture
def hmdrt_run(hmdrt_config: Callable[..., Path], hmdrt_compositor: Callable[..., Recording]) -> Callable[..., Report]:
    """hmdrt_run(config=None, *, frames=30, virtual_time=True, seed=0, timeout_s=120, **config_keys): run a
    compositor for `frames` VSyncs and return its report as a Report (report.latency_ms.gaze_to_photon.p99).

    Without a config file, config_keys go to hmdrt_config (method, eyes, trace, sections). In virtual time a run
    never misses and reproduces bit for bit; in real time it measures this machine. A run past timeout_s fails the
    test.
    """
    from hmdrt.testing.runs import run_bounded

    def run(
        config: Path | None = None,
        *,
        frames: int = 30,
        virtual_time: bool = True,
        seed: int = 0,
        timeout_s: float = 120.0,
        **config_keys: Any,
    ) -> Report:
        if config is not None and config_keys:
            raise TypeError(f"hmdrt_run: give a config file or config keys ({', '.join(config_keys)}), not both")
        path = config if config is not None else hmdrt_config(**config_keys)
        comp = hmdrt_compositor(path, frames=frames, virtual_time=virtual_time, seed=seed)
        report, _ = run_bounded(comp, timeout_s)
        return Report(report)

    return run


@pytest.fixture
def hmdrt_emulator() -> Iterator[Callable[..., Emulator]]:
    """hmdrt_emulator(device, **options): a started emulated tracker (smi, fove, pupil on a free loopback port;
    razor, hatire on a pseudo-terminal) whose `url` goes into a config's drivers; options as
    drivers.emulators.make_emulator takes them (seed, rate_hz, offset_deg, noise_deg, latency_ms, trace). Stopped
    when the test ends. Emulators run on the host clock: they feed real-time runs."""
    from hmdrt.drivers.emulators import REGISTRY, make_emulator

    started: list[Emulator] = []

    def start(device: str, **options: Any) -> Emulator:
        if device in REGISTRY and REGISTRY[device].device.port is not None:  # a free port where it takes one
            options.setdefault("port", 0)
        emulator = make_emulator(device, **options).start()
        started.append(emulator)
        return emulator

    yield start
    for emulator in reversed(started):
        emulator.stop()
