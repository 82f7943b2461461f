"""Rendering methods by name. Each composes the shared tracer (trace.integrator.Whitted) and the
shared stages (foveation.stages) and registers itself (registry.register); "name?key=value&..." selects a
method with options."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from urllib.parse import parse_qsl

import msgspec
import msgspec.inspect

from hmdrt.errors import ConfigError
from hmdrt.foveation.base import FrameRequest, Method
from hmdrt.foveation.registry import METHODS
from hmdrt.trace.integrator import Whitted

# the method modules, each registering its classes as it loads; METHODS keeps this order, which the CLI's help and
# the live page's list of methods show
for _module in ("reference", "rrm", "kim21", "weier16", "weier18"):
    importlib.import_module(f"{__name__}.{_module}")

__all__ = ["METHODS", "FrameRequest", "Method", "MethodChoice", "make_method"]


def _text(value) -> str:
    """An option's value as a spec writes it: true/false, a list's values joined by commas."""
    if isinstance(value, (list, tuple)):
        return ",".join(_text(v) for v in value)
    return str(value).lower() if isinstance(value, bool) else str(value)


def _split_lists(fields: dict, params_type: type[msgspec.Struct]) -> dict:
    """The fields with each string given to a list-valued option split at its commas, as _text writes lists."""
    listed = {
        f.name
        for f in msgspec.inspect.type_info(params_type).fields
        if isinstance(f.type, (msgspec.inspect.ListType, msgspec.inspect.TupleType, msgspec.inspect.VarTupleType))
    }
    return {k: v.split(",") if k in listed and isinstance(v, str) else v for k, v in fields.items()}


@dataclass(frozen=True)
class MethodChoice:
    """A method by name and its validated parameters. Strings ("name?key=value&...", as the CLI, TOML files and
    the control socket give them) are parsed once, by parse(), and the choice travels as it is from there;
    str() writes it back with the fields that differ from the method's defaults, which parse() reads again."""

    name: str
    params: msgspec.Struct

    @classmethod
    def parse(cls, spec: str, **options) -> MethodChoice:
        """The choice of "name?key=value&..." with keyword options over the spec's; ConfigError names what is wrong."""
        name, _, query = spec.partition("?")
        try:
            given = dict(parse_qsl(query, keep_blank_values=True, strict_parsing=bool(query)))
        except ValueError:
            raise ConfigError(f"method options must look like ?key=value&key=value, got {query!r}") from None
        return cls._of(name, {**given, **options})

    @classmethod
    def _of(cls, name: str, fields: dict) -> MethodChoice:
        if name not in METHODS:
            raise ConfigError(f"unknown method {name!r}; methods: {', '.join(METHODS)}")
        params_type = METHODS[name].Params
        try:
            return cls(name, msgspec.convert(_split_lists(fields, params_type), params_type, strict=False))
        except msgspec.ValidationError as exc:
            names = ", ".join(params_type.__struct_fields__) or "none"
            raise ConfigError(f"method {name!r}: {exc} (options: {names})") from None

    def with_options(self, **options) -> MethodChoice:
        """The same method with these fields changed, validated as parse() validates them."""
        return self._of(self.name, {**msgspec.to_builtins(self.params), **options})

    def make(self, tracer: Whitted) -> Method:
        return METHODS[self.name](tracer, self.params)

    def __str__(self) -> str:
        defaults = METHODS[self.name].Params()
        fields = ((f, getattr(self.params, f)) for f in self.params.__struct_fields__)
        changed = [f"{f}={_text(v)}" for f, v in fields if v != getattr(defaults, f)]
        return f"{self.name}?{'&'.join(changed)}" if changed else self.name


def make_method(choice: MethodChoice | str, tracer: Whitted, **options) -> Method:
    """The method of a choice, or of a spec string ("weier16", "weier16?frc=small", ...) with options over it."""
    if isinstance(choice, str):
        choice = MethodChoice.parse(choice, **options)
    elif options:
        choice = choice.with_options(**options)
    return choice.make(tracer)
