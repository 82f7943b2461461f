"""GazeBase CSV files (desktop EyeLink 1000 recordings of the left eye at 1000 Hz) as gaze traces.

GazeBase (Griffith, Lohr, Abdulin and Komogortsev 2021, "GazeBase, a large-scale, multi-stimulus, longitudinal
eye movement dataset", Scientific Data 8:184; CC BY 4.0, on figshare) has one CSV per subject, session and task.
Columns used: n (time in ms from the recording's start), x, y (the left eye's gaze in degrees of visual angle
from the screen centre), val (0: a valid sample; GazeBase writes x, y and dP of any other as NaN); the pupil
area dP, the event label lab and a task's target xT, yT are ignored. Both `n,x,y,val,dP,lab,xT,yT` and
`n,x,y,val,xT,yT,dP,lab` occur in the dataset, so columns are found by name.

Angles are read as yaw = x, positive to the right, and pitch = y, positive up, as GazeBaseVR's are: the first
rows of a reading (TEX) recording (tests/data/traces/gazebase_example.csv) sit at x = -16, y = +5.9, the text's
top left. A sample is valid when val is 0 and x, y are within +-90 degrees; it gives L, the recorded eye. A val,
x or y that is no number (NaN aside) makes the row malformed.
"""

from __future__ import annotations

from pathlib import Path

from hmdrt.bus.messages import Gaze
from hmdrt.replay.formats import MS, direction, gaze_sample, number, read_csv, time_ns
from hmdrt.replay.trace import TraceReading

COLUMNS = ("n", "x", "y", "val")
NAME, NEEDS = "GazeBase", f"[{', '.join(COLUMNS)}]"


def matches(header: list[str]) -> bool:
    """Whether a CSV header is GazeBase's (GazeBaseVR's, which has no val, is tried first)."""
    return set(COLUMNS) <= set(header)


def _sample(row: dict[str, str], seq: int) -> Gaze:
    gaze = direction(number(row["x"]), number(row["y"]))
    return gaze_sample(seq, time_ns(row["n"], MS), number(row["val"]) == 0.0, L=gaze)


def read_gazebase_desktop(path: str | Path) -> TraceReading:
    """Gaze samples of a GazeBase CSV file; malformed rows are counted in TraceReading.malformed."""
    return read_csv(Path(path), "gazebase", _sample)
