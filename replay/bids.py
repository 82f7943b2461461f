"""A trace's gaze as BIDS eye-tracking data: one `_physio.tsv.gz` and its JSON sidecar per eye.

Follows the BIDS specification's "Physiological recordings" and its "Eye-tracking" section (BEP020, part of
BIDS since 1.11.0), checked against the schema of bidsschematools 2.0.1 (BIDS 1.11.2) and by bids-validator 3.0.2:

- Files: OUT names the recording, `<matches>_physio.tsv.gz` (e.g. `sub-01_task-replay_physio.tsv.gz`, to be placed in
  a dataset's `sub-<label>/beh/`); every eye the trace has gets `<matches>_recording-<label>_physio.tsv.gz` and
  `.json`, with the labels the spec recommends: eye1 the left eye (L), eye2 the right (R), eye3 the cyclopean gaze
  (hmdrt's combined C), and `RecordedEye` saying which.
- Columns, without a header row as the spec requires: `timestamp` (ms on the trace's own clock, t_host, written
  exactly to the nanosecond), `x_coordinate`, `y_coordinate`.
- Coordinates: `SampleCoordinateSystem` "eye-in-head", x the yaw and y the pitch in degrees of the gaze direction in
  the head frame (yaw positive right, pitch positive up; hmdrt.spatial.gaze_angles). That is what every hmdrt trace
  holds, HMD or screen-based, so no screen is described: `ScreenSize`, `ScreenDistance` and `ScreenResolution`
  (REQUIRED only with "gaze-on-screen") are not written. For an EyeLink source the screen geometry options
  (screen_width_mm, screen_height_mm, distance_mm) are what turn its pixels into these angles.
- An invalid sample, or an eye a sample lacks, is `n/a` in that eye's file; every file has every gaze sample's row.
- Sidecar: the REQUIRED `SamplingFrequency` (the rate of the median sample interval: a trace need not be sampled
  regularly, and the timestamp column holds each sample's time), `StartTime` 0 (the recording is its own time
  origin: there is no other data to align it to), `Columns`, `PhysioType` "eyetrack", `RecordedEye`,
  `SampleCoordinateSystem`; `Description` and `Units` of each column; `TaskName` when the name has a task entity.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Iterable, Iterator
from decimal import Decimal
from pathlib import Path

import numpy as np

from hmdrt.bus.messages import Gaze
from hmdrt.errors import ConfigError
from hmdrt.files.atomic import write_atomic
from hmdrt.replay.table import GAZE, SampleTable
from hmdrt.replay.trace import Sample, batches, write_chunks
from hmdrt.spatial import gaze_angles

SUFFIX = "_physio.tsv.gz"
RECORDINGS = {"L": ("eye1", "left"), "R": ("eye2", "right"), "C": ("eye3", "cyclopean")}  # eye: (label, RecordedEye)
COLUMNS = ("timestamp", "x_coordinate", "y_coordinate")
COLUMN_METADATA = {
    "timestamp": {
        "Description": "Time of the sample on the trace's own clock (hmdrt's t_host)",
        "Units": "ms",
    },
    "x_coordinate": {
        "LongName": "Gaze yaw",
        "Description": "Horizontal angle of the gaze direction in the head frame, positive to the right",
        "Units": "deg",
    },
    "y_coordinate": {
        "LongName": "Gaze pitch",
        "Description": "Vertical angle of the gaze direction in the head frame, positive up",
        "Units": "deg",
    },
}


def _stem(out: Path) -> str:
    """OUT's name without `_physio.tsv.gz`; a ConfigError for a name that is not a BIDS physio file of ours."""
    if not out.name.endswith(SUFFIX):
        raise ConfigError(f"{out.name}: a BIDS eye-tracking file's name ends in {SUFFIX}")
    stem = out.name.removesuffix(SUFFIX)
    if re.search(r"(^|_)recording-", stem):
        raise ConfigError(f"{out.name}: leave out the recording-<label> entity; each eye's file gets its own")
    return stem


def physio_files(out: str | Path, samples: Iterable[Sample]) -> dict[str, tuple[Path, Path]]:
    """The (TSV, sidecar) pair per eye ("L", "R", "C") that write_physio writes for these samples."""
    out = Path(out)
    stem = _stem(out)
    table = SampleTable.of(samples)
    files = {}
    for eye, (label, _) in RECORDINGS.items():
        if table.present(eye):
            name = f"{stem}_recording-{label}_physio"
            files[eye] = (out.with_name(name + ".tsv.gz"), out.with_name(name + ".json"))
    return files


def _sampling_frequency(table: SampleTable) -> float:
    """The rate of the median interval between consecutive gaze samples, in Hz."""
    times = table.column("t_host")[table.column("kind") == GAZE]
    steps = np.diff(times)
    steps = steps[steps > 0]
    if not len(steps):
        raise ConfigError("a BIDS recording needs at least two gaze samples at different times")
    return float(f"{1e9 / float(np.median(steps)):.6g}")


def _cell(value: float) -> str:
    return repr(value) if math.isfinite(value) else "n/a"


def _rows(table: SampleTable, eye: str) -> Iterator[bytes]:
    """One eye's TSV rows, a batch of samples at a time."""
    for batch in batches(s for s in table if isinstance(s, Gaze)):
        rows = []
        for s in batch:
            v = getattr(s, eye)
            x, y = gaze_angles(v) if s.valid and v is not None else (math.nan, math.nan)
            rows.append(f"{Decimal(s.t_host).scaleb(-6):f}\t{_cell(x)}\t{_cell(y)}\n")
        yield "".join(rows).encode()


def write_physio(out: str | Path, samples: Iterable[Sample]) -> list[Path]:
    """Write the gaze samples as BIDS eye-tracking physio files beside OUT (see the module docstring); the paths."""
    out = Path(out)
    table = SampleTable.of(samples)
    files = physio_files(out, table)
    if not files:
        raise ConfigError(f"{out.name}: the trace has no gaze direction to export")
    frequency = _sampling_frequency(table)
    task = re.search(r"(?:^|_)task-([a-zA-Z0-9]+)", out.name)
    written = []
    for eye, (tsv, sidecar) in files.items():
        metadata = {
            "SamplingFrequency": frequency,
            "StartTime": 0,
            "Columns": list(COLUMNS),
            "PhysioType": "eyetrack",
            "RecordedEye": RECORDINGS[eye][1],
            "SampleCoordinateSystem": "eye-in-head",
            **({"TaskName": task.group(1)} if task else {}),
            **COLUMN_METADATA,
        }
        write_chunks(tsv, _rows(table, eye))
        write_atomic(sidecar, (json.dumps(metadata, indent=2) + "\n").encode())
        written += [tsv, sidecar]
    return written
