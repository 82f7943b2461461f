"""TOML config files read and validated into msgspec structs, every mistake reported as one ConfigError line."""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import TypeVar

import msgspec

from hmdrt.errors import ConfigError

T = TypeVar("T")


def read_toml(path: str | Path) -> dict:
    """The tables of a TOML file; a missing, unreadable or invalid file is a ConfigError."""
    path = Path(path)
    try:
        return tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"config not found: {path}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read config {path}: {exc}") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path} is not valid TOML: {exc}") from None


def convert(data: dict, kind: type[T], source: str | Path | None) -> T:
    """`data` validated as `kind`; the first mistake, with where it is, as a ConfigError."""
    try:
        return msgspec.convert(data, kind)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{source or 'config'}: {exc}") from None
