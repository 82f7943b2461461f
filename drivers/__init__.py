"""Device drivers, found by URL scheme as pyserial finds loop://.

    open_driver("synthetic://?seed=1&rate=250")
    open_driver("replay://trace.jsonl?speed=1&loop=0")
    open_driver("smi://127.0.0.1:4444?listen=5555")

Adding a driver is one module with a Driver subclass and one entry in REGISTRY (or register()).
Modules are imported only when their scheme is used, so a missing optional dependency of one
driver never stops the others.
"""

from __future__ import annotations

import importlib

from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DeviceLost, Driver, DriverError, DriverNotFound, DriverUrl

REGISTRY: dict[str, str] = {
    "synthetic": "hmdrt.drivers.synthetic:SyntheticDriver",
    "replay": "hmdrt.drivers.replay:ReplayDriver",
    "smi": "hmdrt.drivers.smi:SmiDriver",
    "fove": "hmdrt.drivers.fove:FoveDriver",
    "pupil": "hmdrt.drivers.pupil:PupilDriver",
    "hid": "hmdrt.drivers.hid:HidDriver",
    "serial": "hmdrt.drivers.serial_port:SerialDriver",
    "lsl": "hmdrt.drivers.lsl:LslDriver",
}

__all__ = [
    "REGISTRY",
    "DeviceLost",
    "Driver",
    "DriverError",
    "DriverNotFound",
    "DriverUrl",
    "driver_class",
    "open_driver",
    "register",
]


def register(scheme: str, target: str) -> None:
    """Make URL scheme `scheme` resolve to "module:Class"."""
    REGISTRY[scheme] = target


def driver_class(scheme: str) -> type[Driver]:
    if scheme not in REGISTRY:
        raise DriverNotFound(f"no driver for {scheme}://; drivers: {', '.join(s + '://' for s in REGISTRY)}")
    module, _, name = REGISTRY[scheme].partition(":")
    try:
        return getattr(importlib.import_module(module), name)
    except ImportError as exc:
        raise DriverError(f"the {scheme}:// driver cannot load: {exc}") from exc


def open_driver(url: str, clock: Clock = MONOTONIC) -> Driver:
    """The driver for a URL, configured but not yet opened."""
    parsed = DriverUrl.parse(url)
    return driver_class(parsed.scheme)(parsed, clock)
