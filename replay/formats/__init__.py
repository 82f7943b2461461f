"""What the importers of foreign trace formats share: capped text reading, CSV rows, time columns,
gaze angles and vectors, and the normalised sample they all produce.

Every importer turns a file into a TraceReading of Gaze samples numbered in file order, with t_host =
t_dev = the file's own time in integer nanoseconds (relative values kept, so replay can re-base
them). A line that does not parse is counted in TraceReading.malformed and skipped; a file that
yields no valid sample is a ConfigError. Files are read a line at a time under the native format's size caps, into a
SampleTable (replay/table.py) under its cap on samples; a CSV's header is its first line that is not blank.
"""

from __future__ import annotations

import csv
import gzip
import math
from collections.abc import Callable, Iterator
from decimal import Decimal
from pathlib import Path

from hmdrt.bus.messages import Gaze
from hmdrt.errors import ConfigError
from hmdrt.replay.table import SampleTable
from hmdrt.replay.trace import TraceReading, capped_lines, first_line, open_capped
from hmdrt.spatial import gaze_direction

NS, MS, S = 1, 1_000_000, 1_000_000_000  # nanoseconds per unit of a time column
MAX_TIME_NS = 2**62
SHOWN_COLUMNS, SHOWN_CHARS = 24, 40  # how much of a refused header its error message quotes
Vec3 = tuple[float, float, float]


def text_lines(path: Path) -> Iterator[str | None]:
    """Lines of a text file (gzip when it ends in .gz) under the trace size caps; None for an over-long line."""
    try:
        with open_capped(path) as stream:
            for line in capped_lines(stream):
                yield None if line is None else line.decode("utf-8", "replace").rstrip("\r\n")
    except (OSError, EOFError, gzip.BadGzipFile) as exc:
        raise ConfigError(f"cannot read trace {path}: {exc}") from None


def _cells(line: str) -> list[str]:
    """The cells of one CSV line (csv.Error for a line the csv module refuses, e.g. one with NUL)."""
    return next(csv.reader([line]), [])


def _names(line: str | None) -> list[str]:
    try:
        return [name.strip() for name in _cells((line or "").lstrip("\ufeff"))]
    except csv.Error:
        return []


def csv_header(path: Path) -> list[str]:
    """The column names of a CSV file's header row (empty when the file has none)."""
    lines = text_lines(path)
    try:
        return _names(first_line(lines))
    finally:
        lines.close()


def refuse_columns(path: Path, header: list[str], needs: dict[str, str]) -> ConfigError:
    """The error for a CSV no format reads: the columns it has (the first few, cut short) and what each needs."""
    shown = [name if len(name) <= SHOWN_CHARS else name[:SHOWN_CHARS] + "..." for name in header[:SHOWN_COLUMNS]]
    more = f", ... ({len(header)} in all)" if len(header) > SHOWN_COLUMNS else ""
    found = f"found columns [{', '.join(shown)}{more}]" if header else "found no columns"
    wanted = "; ".join(f"{name} needs {columns}" for name, columns in needs.items())
    return ConfigError(f"{path} is not a known gaze CSV: {found}; {wanted}")


def number(text: str) -> float:
    """A numeric cell; empty, '.', 'nan' are missing values (NaN). ValueError for anything else."""
    text = text.strip()
    return math.nan if text in ("", ".") else float(text)


def time_ns(text: str, unit_ns: int) -> int:
    """A time cell in units of unit_ns as integer nanoseconds, exact for decimal text (ValueError if not a time)."""
    try:
        value = Decimal(text.strip()) * unit_ns
    except ArithmeticError:  # InvalidOperation: not a number; Overflow: an exponent past the decimal context's
        raise ValueError(f"not a time: {text!r}") from None
    if not value.is_finite() or abs(value) > MAX_TIME_NS:
        raise ValueError(f"time out of range: {text!r}")
    return int(value.to_integral_value())


def unit(x: float, y: float, z: float) -> Vec3 | None:
    """The unit vector along (x, y, z); None when a component is missing or the vector is zero."""
    norm = math.sqrt(x * x + y * y + z * z)
    if not (math.isfinite(norm) and norm > 0.0):
        return None
    return (x / norm, y / norm, z / norm)


def direction(yaw_deg: float, pitch_deg: float) -> Vec3 | None:
    """Head-frame gaze direction for yaw (right +) and pitch (up +) in degrees; None when missing or beyond +-90."""
    if not (abs(yaw_deg) <= 90.0 and abs(pitch_deg) <= 90.0):  # also false for NaN
        return None
    return gaze_direction(yaw_deg, pitch_deg)


def gaze_sample(
    seq: int,
    t_ns: int,
    valid: bool,
    C: Vec3 | None = None,
    L: Vec3 | None = None,
    R: Vec3 | None = None,
    depth_m: float | None = None,
) -> Gaze:
    """An imported sample: the file's time as t_host and t_dev; valid only when it carries a direction."""
    if depth_m is not None and not (0.0 < depth_m <= 1e6):
        depth_m = None
    has_gaze = any(v is not None for v in (C, L, R))
    return Gaze(seq=seq, t_host=t_ns, t_dev=t_ns, valid=valid and has_gaze, C=C, L=L, R=R, depth_m=depth_m)


def require_valid(path: Path, reading: TraceReading) -> TraceReading:
    """The reading, or a ConfigError when the file held no valid sample of its format."""
    if not SampleTable.of(reading.samples).column("valid").any():
        raise ConfigError(
            f"{path} holds no valid {reading.device} gaze samples "
            f"({len(reading.samples)} samples read, {reading.malformed} malformed lines)"
        )
    return reading


def read_csv(path: Path, device: str, convert: Callable[[dict[str, str], int], Gaze]) -> TraceReading:
    """Samples of a CSV file whose header row names the columns; convert(row, seq) makes one sample.

    Rows of the wrong width, over-long lines and rows that convert raises ValueError for are counted
    as malformed; blank lines are skipped.
    """
    reading = TraceReading(device, SampleTable(f"trace {path}"))
    lines = text_lines(path)
    names = _names(first_line(lines))
    for line in lines:
        if line is None:
            reading.malformed += 1
            continue
        if not line.strip():
            continue
        try:
            row = dict(zip(names, _cells(line), strict=True))  # ValueError for a row of the wrong width
            reading.samples.append(convert(row, len(reading.samples)))
        except (ValueError, csv.Error):
            reading.malformed += 1
    return require_valid(path, reading)
