"""TOML config files read and validated into msgspec structs, every mistake reported as one ConfigError line."""

from __future__ import annotations

import os
import stat
import tomllib
from pathlib import Path
from typing import TypeVar

import msgspec

from hmdrt.errors import ConfigError

T = TypeVar("T")

# Configs, profiles and scene descriptions are a few KB; a larger file is refused before more is read
# (a size from stat alone would let /dev/zero or a FIFO through).
MAX_TOML_BYTES = 4 * 1024 * 1024


def read_capped(path: Path, limit: int) -> bytes | None:
    """The bytes of a file, or None when it holds more than `limit`; OSError when it cannot be read. Read in
    steps from the size stat gives, so a file that stat cannot size (a device, a FIFO) or that is still growing
    costs at most limit + 1 bytes, and a small file no more than its size."""
    chunks, total = [], 0
    with path.open("rb") as f:
        step = min(os.fstat(f.fileno()).st_size, limit) + 1
        while chunk := f.read(step):
            chunks.append(chunk)
            total += len(chunk)
            if total > limit:
                return None
            step = min(1 << 20, limit + 1 - total)
    return b"".join(chunks)


def parse_toml(data: bytes) -> dict:
    """The tables of a TOML document; ValueError when it is not UTF-8, not TOML, or nested too deeply."""
    try:
        return tomllib.loads(data.decode("utf-8"))
    except RecursionError:  # tomllib recurses once per level of nested arrays and inline tables
        raise ValueError("arrays or inline tables nested too deeply") from None


def read_limited(
    path: Path, what: str, limit: int = MAX_TOML_BYTES, error: type[Exception] = ConfigError, regular_only: bool = False
) -> bytes:
    """The bytes of file `path` (a `what`: "config", "texture image", ...), at most `limit`; a missing, unreadable
    or larger file, or with regular_only one that is not a regular file (a device or FIFO that may never end),
    is one `error` line."""
    try:
        info = path.stat()
        regular = stat.S_ISREG(info.st_mode)
        if regular_only and not regular:
            raise error(f"{what} {path} is not a regular file")
        data = None if regular and info.st_size > limit else read_capped(path, limit)  # capped: it may have grown
    except FileNotFoundError:
        raise error(f"{what} not found: {path}") from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path
        raise error(f"cannot read {what} {path}: {getattr(exc, 'strerror', None) or exc}") from None
    if data is None:
        raise error(f"{what} {path} is larger than the limit of {limit} bytes")
    return data


def read_toml(path: str | Path) -> dict:
    """The tables of a TOML file; a missing, unreadable, oversized or invalid file is a ConfigError."""
    path = Path(path)
    data = read_limited(path, "config")
    try:
        return parse_toml(data)
    except UnicodeDecodeError as exc:
        raise ConfigError(f"cannot read config {path}: {exc}") from None
    except ValueError as exc:  # tomllib.TOMLDecodeError, or nested too deeply
        raise ConfigError(f"{path} is not valid TOML: {exc}") from None


def convert(data: dict, kind: type[T], source: str | Path | None) -> T:
    """`data` validated as `kind`; the first mistake, with where it is, as a ConfigError."""
    try:
        return msgspec.convert(data, kind)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"{source or 'config'}: {exc}") from None
