"""Rendering methods by name. Each composes the shared tracer (trace.integrator.Whitted)."""

from __future__ import annotations

import inspect
from collections.abc import Callable

from hmdrt.errors import ConfigError
from hmdrt.foveation.base import FrameRequest, Method
from hmdrt.foveation.reference import Full, Regular
from hmdrt.trace.integrator import Whitted

METHODS: dict[str, Callable[..., Method]] = {"full": Full, "regular": Regular}

__all__ = ["METHODS", "FrameRequest", "Method", "make_method"]


def make_method(name: str, tracer: Whitted, **options) -> Method:
    """The method `name` over `tracer`, with its options (e.g. spp for regular)."""
    if name not in METHODS:
        raise ConfigError(f"unknown method {name!r}; methods: {', '.join(METHODS)}")
    accepted = [p for p in inspect.signature(METHODS[name]).parameters if p != "tracer"]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise ConfigError(f"method {name!r} has no option {unknown[0]!r}; options: {', '.join(accepted) or 'none'}")
    return METHODS[name](tracer, **options)
