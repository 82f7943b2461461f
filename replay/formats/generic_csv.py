"""hmdrt's own CSV gaze format, for traces made by hand or by other tools.

The header row (the first line that is not blank) names the columns (any order; others are ignored):

    t_ns | t_ms | t_s        the sample's time on the file's own clock (exactly one of them)
    yaw_deg, pitch_deg       combined gaze C as angles: yaw positive right, pitch positive up
    cx, cy, cz               or combined gaze C as a direction in the head frame (+X right, +Y up,
                             -Z forward); directions are normalised on reading
    lx, ly, lz, rx, ry, rz   per-eye directions L and R (either eye or both)
    valid                    optional: 1/0 or true/false (default true)
    depth_m                  optional vergence depth in metres

    t_ms,yaw_deg,pitch_deg,valid
    0,0.0,0.0,1
    4,1.5,-2.0,1

An empty or NaN gaze cell leaves that gaze out and makes the sample invalid; a row whose cells are
not numbers is counted as malformed.
"""

from __future__ import annotations

from pathlib import Path

from hmdrt.bus.messages import Gaze
from hmdrt.errors import ConfigError
from replay.formats import MS, NS, S, csv_header, direction, gaze_sample, number, read_csv, time_ns, unit
from replay.trace import TraceReading

TIME_COLUMNS = {"t_ns": NS, "t_ms": MS, "t_s": S}
ANGLES = ("yaw_deg", "pitch_deg")
VECTORS = {"C": ("cx", "cy", "cz"), "L": ("lx", "ly", "lz"), "R": ("rx", "ry", "rz")}
FLAGS = {"1": True, "true": True, "0": False, "false": False}
NAME, NEEDS = "hmdrt CSV", f"one of [{', '.join(TIME_COLUMNS)}] and gaze columns"


def matches(header: list[str]) -> bool:
    """Whether a CSV header has a time column of this format."""
    return any(name in header for name in TIME_COLUMNS)


def _schema(path: Path, header: list[str]) -> tuple[str, dict[str, tuple[str, ...]]]:
    """The time column and the gaze columns per eye, or a ConfigError naming what is wrong."""
    times = [name for name in TIME_COLUMNS if name in header]
    if len(times) != 1:
        raise ConfigError(f"{path} needs exactly one time column of t_ns, t_ms, t_s; it has {times or 'none'}")
    groups = {eye: cols for eye, cols in VECTORS.items() if any(c in header for c in cols)}
    if any(c in header for c in ANGLES):
        groups.setdefault("C", ANGLES)
        if groups["C"] != ANGLES:
            raise ConfigError(f"{path} gives the combined gaze twice: as yaw_deg, pitch_deg and as cx, cy, cz")
    for cols in groups.values():
        if missing := [c for c in cols if c not in header]:
            raise ConfigError(f"{path} has {', '.join(c for c in cols if c in header)} but not {', '.join(missing)}")
    if not groups:
        raise ConfigError(f"{path} has no gaze columns (yaw_deg,pitch_deg or cx,cy,cz or lx,ly,lz / rx,ry,rz)")
    return times[0], groups


def read_generic_csv(path: str | Path) -> TraceReading:
    """Gaze samples of a CSV file in hmdrt's schema; malformed rows are counted in TraceReading.malformed."""
    path = Path(path)
    time_column, groups = _schema(path, csv_header(path))

    def sample(row: dict[str, str], seq: int) -> Gaze:
        gaze = {}
        for eye, cols in groups.items():
            values = [number(row[c]) for c in cols]
            gaze[eye] = direction(*values) if cols == ANGLES else unit(*values)
        flag = row.get("valid", "1").strip().lower()
        if flag not in FLAGS:
            raise ValueError(f"valid must be 1/0/true/false, got {flag!r}")
        valid = FLAGS[flag] and all(v is not None for v in gaze.values())
        depth = number(row["depth_m"]) if "depth_m" in row else None
        return gaze_sample(seq, time_ns(row[time_column], TIME_COLUMNS[time_column]), valid, depth_m=depth, **gaze)

    return read_csv(path, "csv", sample)
