"""Emulators: servers (and the hid:// stub device) that speak a real tracker's protocol, fed by traces or
synthetic motion. make_emulator() builds one by name, as `hmdrt emulate` does."""

from __future__ import annotations

import importlib

from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.emulators.base import Emulator
from hmdrt.drivers.emulators.feed import GazeFeed
from hmdrt.errors import ConfigError

# name -> (class, default port (None: found by LSL's discovery, no port), default rate Hz, default latency ms)
EYE_TRACKERS = {
    "smi": ("hmdrt.drivers.emulators.smi_server:SmiEmulator", 4444, 250.0, 0.0),
    "fove": ("hmdrt.drivers.emulators.fove_server:FoveEmulator", 50050, 120.0, 20.0),
    "pupil": ("hmdrt.drivers.emulators.pupil_server:PupilEmulator", 50020, 200.0, 0.0),
    "lsl": ("hmdrt.drivers.emulators.lsl_source:LslEmulator", None, 120.0, 0.0),
}
HEAD_TRACKERS = ("razor", "hatire")  # serial, behind a pseudo-terminal
EMULATORS = (*EYE_TRACKERS, *HEAD_TRACKERS)


def _load(target: str) -> type[Emulator]:
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)


def make_emulator(
    device: str,
    host: str = "127.0.0.1",
    port: int | None = None,
    trace: str | None = None,
    seed: int = 0,
    rate_hz: float | None = None,
    offset_deg: float | None = None,
    noise_deg: float | None = None,
    latency_ms: float | None = None,
    clock: Clock = MONOTONIC,
) -> Emulator:
    """An emulated tracker, not yet started. Eye trackers take their gaze from `trace` or the
    synthetic generator of `seed`, degraded by offset_deg, noise_deg and latency_ms; the serial head
    trackers follow the synthetic head motion of `seed`."""
    if device in HEAD_TRACKERS:
        given = {
            "--port": port,
            "--trace": trace,
            "--offset": offset_deg,
            "--noise": noise_deg,
            "--latency": latency_ms,
        }
        if unused := [flag for flag, value in given.items() if value is not None]:
            raise ConfigError(f"the {device} emulator is a head tracker on a pseudo-terminal; it takes no {unused[0]}")
        from hmdrt.drivers.emulators.serial_emulator import SerialTrackerEmulator

        return SerialTrackerEmulator(device, rate_hz=rate_hz, seed=seed, clock=clock)
    if device not in EYE_TRACKERS:
        raise ConfigError(f"no emulator {device!r}; emulators: {', '.join(EMULATORS)}")
    target, default_port, default_rate, default_latency = EYE_TRACKERS[device]
    if default_port is None and port is not None:
        raise ConfigError(f"the {device} emulator is found by LSL's discovery, not at a port; it takes no --port")
    port = default_port if port is None else port
    if port is not None and not 0 <= port <= 65535:
        raise ConfigError(f"--port must be within 0 and 65535 (0: any free port), got {port}")
    for flag, value, lo, hi in (
        ("--offset", offset_deg, -45.0, 45.0),
        ("--noise", noise_deg, 0.0, 10.0),
        ("--latency", latency_ms, 0.0, 1000.0),
    ):
        if value is not None and not lo <= value <= hi:
            raise ConfigError(f"{flag} must be within {lo:g} and {hi:g}, got {value}")
    feed = GazeFeed(
        default_rate if rate_hz is None else rate_hz,
        trace=trace,
        seed=seed,
        offset_deg=offset_deg or 0.0,
        noise_deg=noise_deg or 0.0,
        latency_ms=default_latency if latency_ms is None else latency_ms,
        clock=clock,
    )
    if default_port is None:
        return _load(target)(feed=feed, clock=clock)
    options = {"rate_hz": feed.rate_hz} if device != "fove" else {"seed": seed}
    return _load(target)(host=host, port=port, feed=feed, clock=clock, **options)
