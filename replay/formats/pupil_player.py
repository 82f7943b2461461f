"""Pupil Player exports (gaze_positions.csv from the Raw Data Exporter) as gaze traces.

Columns used: gaze_timestamp (Pupil time, s, arbitrary epoch), confidence, gaze_normal0_x/y/z and
gaze_normal1_x/y/z (unit visual axes of eye 0 and eye 1), gaze_point_3d_x/y/z (the 3D gaze point,
mm). Eye 0 is the right eye and eye 1 the left (docs/protocols.md, Pupil), so normal0 -> R, normal1 -> L; a
monocular row fills only its eye's columns. The 3D data is in the world camera's frame (OpenCV: x
right, y down, z forward), which is head-fixed, and becomes the head frame by (x, y, z) -> (x, -y, -z).
C is the direction to gaze_point_3d and depth_m its distance in metres. Rows with confidence below
min_confidence (Pupil's own default, 0.6) or without any 3D gaze are invalid.

Older Pupil Player exports name the time column differently and are read alike: `timestamp,index,...` until
late 2018, then `world_timestamp,world_index,...` (pupil-labs/pupil#1352) until #1444 chose gaze_timestamp
in 2019; in every version it holds the gaze's own time, and the other columns are the same.
"""

from __future__ import annotations

import math
from pathlib import Path

from hmdrt.bus.messages import Gaze
from hmdrt.errors import ConfigError
from hmdrt.replay.formats import S, Vec3, csv_header, gaze_sample, number, read_csv, refuse_columns, time_ns, unit
from hmdrt.replay.trace import TraceReading

HEADERS = {  # time column: the columns that mark an export, newest format first
    "gaze_timestamp": ("gaze_timestamp", "confidence"),
    "world_timestamp": ("world_timestamp", "world_index", "confidence"),
    "timestamp": ("timestamp", "index", "confidence"),
}
NAME, NEEDS = "Pupil Player", " or ".join(f"[{', '.join(columns)}]" for columns in HEADERS.values())
VECTORS = {"R": "gaze_normal0_", "L": "gaze_normal1_", "C": "gaze_point_3d_"}


def _time_column(header: list[str]) -> str | None:
    """The time column of a Pupil Player gaze export's header, of whichever version; None for another header."""
    return next((time for time, columns in HEADERS.items() if set(columns) <= set(header)), None)


def matches(header: list[str]) -> bool:
    """Whether a CSV header is a Pupil Player gaze export's."""
    return _time_column(header) is not None


def _head_frame(row: dict[str, str], prefix: str) -> tuple[Vec3 | None, float]:
    """The head-frame unit vector of an OpenCV-frame column triple, and its length (NaN when absent)."""
    if prefix + "x" not in row:
        return None, math.nan
    x, y, z = (number(row[prefix + axis]) for axis in "xyz")
    return unit(x, -y, -z), math.sqrt(x * x + y * y + z * z)


def read_pupil_player(path: str | Path, min_confidence: float = 0.6) -> TraceReading:
    """Gaze samples of a Pupil Player gaze_positions.csv; malformed rows are counted in TraceReading.malformed."""
    if not (isinstance(min_confidence, int | float) and 0.0 <= min_confidence <= 1.0):
        raise ConfigError(f"Pupil option min_confidence must be within 0 and 1, got {min_confidence!r}")
    path = Path(path)
    header = csv_header(path)
    if (time_column := _time_column(header)) is None:
        raise refuse_columns(path, header, {NAME: NEEDS})

    def sample(row: dict[str, str], seq: int) -> Gaze:
        gaze = {eye: _head_frame(row, prefix) for eye, prefix in VECTORS.items()}
        confident = number(row["confidence"]) >= min_confidence
        depth_m = gaze["C"][1] / 1000.0
        directions = {eye: v for eye, (v, _) in gaze.items()}
        return gaze_sample(seq, time_ns(row[time_column], S), confident, depth_m=depth_m, **directions)

    return read_csv(path, "pupil", sample)
