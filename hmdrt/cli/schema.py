"""A msgspec schema in words, for the reference and `hmdrt ctl --help`: each field's type with its limits (as
msgspec.Meta declares them) and its default as it is written in TOML."""

from __future__ import annotations

import json
from collections.abc import Iterator

import msgspec
from msgspec import inspect as mi


def _number(value: float) -> str:
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    return f"{value:,}" if isinstance(value, int) and abs(value) >= 10_000 else str(value)


def _bounds(t: mi.Type) -> str:
    """A number's limits, e.g. "0 to 1,000", "above 0", "at least 1"."""
    low = (t.ge, "at least") if t.ge is not None else (t.gt, "above") if t.gt is not None else None
    high = (t.le, "at most") if t.le is not None else (t.lt, "below") if t.lt is not None else None
    if low and high and low[1] == "at least" and high[1] == "at most":
        return f"{_number(low[0])} to {_number(high[0])}"
    return ", ".join(f"{bound[1]} {_number(bound[0])}" for bound in (low, high) if bound is not None)


def _length(t: mi.Type, unit: str) -> str:
    low, high = t.min_length, t.max_length
    if low is not None and high is not None:
        return f"{_number(low)} to {_number(high)} {unit}"
    if high is not None:
        return f"at most {_number(high)} {unit}"
    return f"at least {_number(low)} {unit if low > 1 else SINGULAR[unit]}" if low else ""


SINGULAR = {"characters": "character", "entries": "entry"}


def _with(text: str, limits: str) -> str:
    return f"{text} ({limits})" if limits else text


def _either(parts: list[str]) -> str:
    return parts[0] if len(parts) == 1 else f"{', '.join(parts[:-1])} or {parts[-1]}"


def describe(t: mi.Type) -> str:
    """A type in words with its limits, e.g. "number (0 to 1,000)" or "list of string (at least 1 entries)"."""
    if isinstance(t, mi.Metadata):
        return describe(t.type)
    if isinstance(t, mi.UnionType):
        return _either([describe(u) for u in t.types if not isinstance(u, mi.NoneType)])
    if isinstance(t, mi.StrType):
        return _with("string", _length(t, "characters"))
    if isinstance(t, mi.BoolType):
        return "boolean"
    if isinstance(t, mi.IntType | mi.FloatType):
        return _with("integer" if isinstance(t, mi.IntType) else "number", _bounds(t))
    if isinstance(t, mi.LiteralType):
        return _either([f"`{json.dumps(v)}`" for v in t.values])
    if isinstance(t, mi.ListType | mi.SetType | mi.FrozenSetType | mi.VarTupleType):
        return _with(f"list of {describe(t.item_type)}", _length(t, "entries"))
    if isinstance(t, mi.DictType):
        return _with(f"table of {describe(t.key_type)} to {describe(t.value_type)}", _length(t, "entries"))
    if isinstance(t, mi.StructType):
        return "table"
    return "any value"


def description(t: mi.Type) -> str:
    """The description a field's msgspec.Meta gives ("" if none)."""
    if isinstance(t, mi.Metadata):
        return (t.extra_json_schema or {}).get("description") or description(t.type)
    if isinstance(t, mi.UnionType):
        return next((d for d in map(description, t.types) if d), "")
    return ""


def toml(value: object) -> str:
    """A default value as TOML writes it."""
    if isinstance(value, msgspec.Struct):
        fields = msgspec.structs.fields(value)
        given = {f.name: getattr(value, f.name) for f in fields if getattr(value, f.name) != _default(f)}
        return "{" + ", ".join(f"{k} = {toml(v)}" for k, v in given.items()) + "}"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(map(toml, value)) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {toml(v)}" for k, v in value.items()) + "}"
    return json.dumps(value)


def _default(field: msgspec.structs.FieldInfo | mi.Field) -> object:
    if field.default is not msgspec.NODEFAULT:
        return field.default
    if field.default_factory is not msgspec.NODEFAULT:
        return field.default_factory()
    return msgspec.NODEFAULT


def default(field: mi.Field) -> str:
    """A field's default in TOML, or "required"."""
    value = _default(field)
    return "required" if value is msgspec.NODEFAULT else toml(value)


def fields(struct: type[msgspec.Struct]) -> Iterator[mi.Field]:
    yield from mi.type_info(struct).fields
