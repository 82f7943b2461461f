"""Emulators: servers (and the hid:// stub device) that speak a real tracker's protocol, fed by traces or
synthetic motion. make_emulator() builds one by device name, as `hmdrt emulate` does.

The registry is typed and knows no device by name: each emulator class declares the devices it serves
(`emulates`: name, default port, rate, latency) and how it builds one (`emulate`), and register(cls) enters
its devices. A test registers its own emulator class the same way.
"""

from __future__ import annotations

from dataclasses import dataclass

from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.emulators.base import Emulated, Emulator, EmulatorOptions
from hmdrt.drivers.emulators.fove_server import FoveEmulator
from hmdrt.drivers.emulators.lsl_source import LslEmulator
from hmdrt.drivers.emulators.pupil_server import PupilEmulator
from hmdrt.drivers.emulators.serial_emulator import SerialTrackerEmulator
from hmdrt.drivers.emulators.smi_server import SmiEmulator
from hmdrt.errors import ConfigError

__all__ = [
    "EMULATORS",
    "EYE_TRACKERS",
    "REGISTRY",
    "Emulated",
    "EmulatorOptions",
    "Registered",
    "make_emulator",
    "register",
]


@dataclass(frozen=True)
class Registered:
    device: Emulated  # as its class declares it
    cls: type[Emulator]  # builds it: cls.emulate(device, options)


REGISTRY: dict[str, Registered] = {}  # device name -> its declaration and class, in the order registered
EMULATORS = REGISTRY.keys()  # the device names `hmdrt emulate` takes (a view: a registered class adds its own)


def register(cls: type[Emulator]) -> type[Emulator]:
    """Enter the devices an emulator class declares in `cls.emulates` (usable as a class decorator)."""
    if not cls.emulates:
        raise TypeError(f"{cls.__name__} declares no device in `emulates`")
    for device in cls.emulates:
        REGISTRY[device.name] = Registered(device, cls)
    return cls


for _cls in (SmiEmulator, FoveEmulator, PupilEmulator, LslEmulator, SerialTrackerEmulator):
    register(_cls)

# the emulators of gaze (the others emulate head trackers)
EYE_TRACKERS = tuple(name for name, entry in REGISTRY.items() if entry.device.latency_ms is not None)


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
    trackers follow the synthetic head motion of `seed`. None: the device's default, as its class declares it."""
    if device not in REGISTRY:
        raise ConfigError(f"no emulator {device!r}; emulators: {', '.join(EMULATORS)}")
    entry = REGISTRY[device]
    options = EmulatorOptions(host, port, trace, seed, rate_hz, offset_deg, noise_deg, latency_ms, clock)
    options.check(entry.device)
    return entry.cls.emulate(entry.device, options)
