"""Rendering methods by name. Each composes the shared tracer (trace.integrator.Whitted) and the
shared stages (foveation.stages); "name?key=value&..." selects a method with options."""

from __future__ import annotations

from urllib.parse import parse_qsl

import msgspec

from hmdrt.errors import ConfigError
from hmdrt.foveation.base import FrameRequest, Method
from hmdrt.foveation.kim21 import Kim21
from hmdrt.foveation.reference import Full, Regular
from hmdrt.foveation.rrm import Rrm
from hmdrt.foveation.weier16 import Weier16
from hmdrt.foveation.weier18 import Weier18
from hmdrt.trace.integrator import Whitted

METHODS: dict[str, type] = {m.name: m for m in (Full, Regular, Rrm, Kim21, Weier16, Weier18)}

__all__ = ["METHODS", "FrameRequest", "Method", "make_method", "method_params", "method_spec"]


def method_spec(spec: str, options: dict) -> str:
    """`spec` ("name" or "name?key=value") with `options` appended as key=value; None values are left out."""
    items = "&".join(f"{k}={str(v).lower() if isinstance(v, bool) else v}" for k, v in options.items() if v is not None)
    return f"{spec}{'&' if '?' in spec else '?'}{items}" if items else spec


def method_params(spec: str, **options) -> tuple[str, msgspec.Struct]:
    """The method name and validated parameters of "name?key=value&..." plus keyword options."""
    name, _, query = spec.partition("?")
    if name not in METHODS:
        raise ConfigError(f"unknown method {name!r}; methods: {', '.join(METHODS)}")
    try:
        merged = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)))
    except ValueError:
        raise ConfigError(f"method options must look like ?key=value&key=value, got {query!r}") from None
    merged.update(options)
    params_type = METHODS[name].Params
    try:
        return name, msgspec.convert(merged, params_type, strict=False)
    except msgspec.ValidationError as exc:
        fields = ", ".join(params_type.__struct_fields__) or "none"
        raise ConfigError(f"method {name!r}: {exc} (options: {fields})") from None


def make_method(spec: str, tracer: Whitted, **options) -> Method:
    """The method of `spec` ("weier16", "weier16?frc=small", ...) over `tracer`; options override the spec."""
    name, params = method_params(spec, **options)
    return METHODS[name](tracer, params)
