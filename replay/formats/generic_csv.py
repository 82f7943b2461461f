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

A gaze whose cells are all empty is absent from that row (a binocular file's row may carry one eye, as a
native sample may); a partly empty or NaN gaze is left out and makes the sample invalid. A row whose cells
are not numbers is counted as malformed.

write_generic_csv writes this schema (t_ns, direction columns, valid, depth_m), so a trace converts to it
and reads back with the same times, validity and directions (hmdrt convert).
"""

from __future__ import annotations

import csv
import io
from collections.abc import Iterable, Iterator
from pathlib import Path

from hmdrt.bus.messages import Gaze
from hmdrt.errors import ConfigError
from hmdrt.replay.formats import MS, NS, S, csv_header, direction, gaze_sample, number, read_csv, time_ns, unit
from hmdrt.replay.table import SampleTable
from hmdrt.replay.trace import Sample, TraceReading, batches, write_chunks

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
            cells = [row[c] for c in cols]
            if any(cell.strip() for cell in cells):  # all empty: the row leaves this eye out
                values = [number(cell) for cell in cells]
                gaze[eye] = direction(*values) if cols == ANGLES else unit(*values)
        flag = row.get("valid", "1").strip().lower()
        if flag not in FLAGS:
            raise ValueError(f"valid must be 1/0/true/false, got {flag!r}")
        valid = FLAGS[flag] and all(v is not None for v in gaze.values())
        depth = number(row["depth_m"]) if "depth_m" in row else None
        return gaze_sample(seq, time_ns(row[time_column], TIME_COLUMNS[time_column]), valid, depth_m=depth, **gaze)

    return read_csv(path, "csv", sample)


def write_generic_csv(path: str | Path, samples: Iterable[Sample]) -> int:
    """Write the gaze samples as hmdrt CSV (gzip when the name ends in .gz) and return how many rows were written.

    Columns: t_ns (t_host), the direction columns of each eye some sample has, valid (1/0), and depth_m when
    some sample has one. Numbers are written in full (repr), so reading back gives the same directions up to
    the reader's normalisation (a few 1e-16). Poses are not part of the format and are skipped. Rows are written
    a batch at a time."""
    path = Path(path)
    table = SampleTable.of(samples)
    eyes = [eye for eye in VECTORS if table.present(eye)]
    if not eyes:
        raise ConfigError(f"{path.name}: no gaze direction to write; hmdrt CSV needs at least one")
    depth = table.present("depth_m")
    header = ["t_ns", *(c for eye in eyes for c in VECTORS[eye]), "valid", *(["depth_m"] if depth else [])]

    def row(s: Gaze) -> list[str]:
        cells = [str(s.t_host)]
        for eye in eyes:
            v = getattr(s, eye)
            cells += ["", "", ""] if v is None else [repr(float(c)) for c in v]
        cells.append("1" if s.valid else "0")
        if depth:
            cells.append("" if s.depth_m is None else repr(float(s.depth_m)))
        return cells

    def chunks() -> Iterator[bytes]:
        yield _csv_text([header])
        for batch in batches(s for s in table if isinstance(s, Gaze)):
            yield _csv_text(row(s) for s in batch)

    write_chunks(path, chunks())
    return table.gaze_count


def _csv_text(rows: Iterable[list[str]]) -> bytes:
    text = io.StringIO()
    csv.writer(text, lineterminator="\n").writerows(rows)
    return text.getvalue().encode()
