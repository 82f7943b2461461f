"""GazeBaseVR CSV files (binocular VR eye tracking at 250 Hz) as gaze traces.

Columns used: n (time in ms), x, y (combined gaze, deg), lx, ly, rx, ry (left and right eye, deg);
the target (xT, yT, zT) and eye centres (clx .. crz) are ignored. Angles are read as yaw = x, positive
to the right, and pitch = y, positive up (GazeBaseVR's Unity frame: +X right, +Y up, +Z forward). The
sign of x shows in the data: converging on a central target, the left eye (clx < 0) turns right
(lx > 0) and the right eye left (rx < 0). C comes from (x, y), L and R from the per-eye angles; a
NaN angle leaves that gaze out and makes the sample invalid.
"""

from __future__ import annotations

from pathlib import Path

from hmdrt.bus.messages import Gaze
from hmdrt.replay.formats import MS, direction, gaze_sample, number, read_csv, time_ns
from hmdrt.replay.trace import TraceReading

COLUMNS = ("n", "x", "y", "lx", "ly", "rx", "ry")
NAME, NEEDS = "GazeBaseVR", f"[{', '.join(COLUMNS)}]"


def matches(header: list[str]) -> bool:
    """Whether a CSV header is GazeBaseVR's."""
    return set(COLUMNS) <= set(header)


def _sample(row: dict[str, str], seq: int) -> Gaze:
    gaze = {
        eye: direction(number(row[yaw]), number(row[pitch]))
        for eye, yaw, pitch in (("C", "x", "y"), ("L", "lx", "ly"), ("R", "rx", "ry"))
    }
    return gaze_sample(seq, time_ns(row["n"], MS), all(v is not None for v in gaze.values()), **gaze)


def read_gazebase(path: str | Path) -> TraceReading:
    """Gaze samples of a GazeBaseVR CSV file; malformed rows are counted in TraceReading.malformed."""
    return read_csv(Path(path), "gazebase_vr", _sample)
