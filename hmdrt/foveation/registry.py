"""The rendering methods by name, each registered by its own module, and the checklists read from them.

A method module decorates its class with @register, as a driver declares its URL scheme: the class carries its name,
its Params (the options "name?key=value&..." may set), its stages, its cost knobs and its Checks (base.Checks), and
nothing above the method modules lists any of that. The lists the checks run (golden images, steady-state
allocations, the method tests, the benches' default methods) are built from the registered classes when asked, so a
method registered at any time, a test's toy included, is in each of them (hmdrt/foveation/README.md).
"""

from __future__ import annotations

import re
from typing import TypeVar

import msgspec

from hmdrt.foveation.base import Checks, Method

METHODS: dict[str, type[Method]] = {}  # by name, in the order the modules registered them
NAME = re.compile(r"[a-z][a-z0-9_]*")  # a spec's name part: no ?, & or = (MethodChoice.parse)

M = TypeVar("M", bound=type)


def register(cls: M) -> M:
    """Class decorator: `cls` is the method named cls.name. Refuses a class that does not declare what the method
    interfaces and the checklists read, and a name another class holds."""
    name = cls.__dict__.get("name")
    if not isinstance(name, str) or not NAME.fullmatch(name):
        raise TypeError(f"{cls.__qualname__} must declare its own name, lower-case letters, digits and _: {name!r}")
    params = getattr(cls, "Params", None)
    if not (isinstance(params, type) and issubclass(params, msgspec.Struct)):
        raise TypeError(f"method {name!r}: Params must be a msgspec.Struct class, got {params!r}")
    for attr, kind in (("stages", tuple), ("knobs", tuple), ("checks", Checks)):
        if not isinstance(getattr(cls, attr, None), kind):
            raise TypeError(f"method {name!r}: {attr} must be a {kind.__name__}")
    held = METHODS.get(name, cls)
    if held is not cls:
        raise ValueError(f"method name {name!r} is taken by {held.__module__}.{held.__qualname__}")
    METHODS[name] = cls
    return cls


def unregister(name: str) -> None:
    """Forget method `name` (a test's toy, once the test is done)."""
    if METHODS.pop(name, None) is None:
        raise KeyError(f"no method {name!r} is registered")


def golden_cases() -> list[tuple[str, str]]:
    """(scene, spec) of every golden image the methods declare: each variant on each of Checks.golden's scenes."""
    return [(scene, spec) for name, cls in METHODS.items() for scene in cls.checks.golden for spec in _specs(name)]


def allocation_cases() -> list[tuple[str, str]]:
    """(scene, spec) the steady-state allocation test runs: the golden cases, the views each method is pinned on."""
    return golden_cases()


def bench_methods() -> list[str]:
    """The specs bench/stage_budget.py and bench/foveation_speedup.py time by default (Checks.bench)."""
    return [spec for name, cls in METHODS.items() if cls.checks.bench for spec in _specs(name)]


def temporal_methods() -> list[str]:
    """The methods that keep history across frames (Checks.temporal), by name."""
    return [name for name, cls in METHODS.items() if cls.checks.temporal]


def _specs(name: str) -> list[str]:
    return METHODS[name].checks.specs(name)
