"""hmdrt convert: any trace load_trace reads, written as native JSONL, hmdrt CSV or BIDS eye-tracking physio.

The output format follows OUT's name: `.jsonl` / `.jsonl.gz` native (replay/trace.py), `.csv` / `.csv.gz` hmdrt CSV
(replay/formats/generic_csv.py), `_physio.tsv.gz` BIDS eye-tracking (replay/bids.py). Native keeps every sample;
hmdrt CSV and BIDS hold gaze only, so head poses are left out (and counted), and they keep one time per sample,
t_host (every imported format has t_dev equal to it; a recorded native trace may not). A refusal (an unknown
output name, an option the input's format does not take, an output that exists without force) is a ConfigError,
before anything is written. The samples are held as a SampleTable (replay/table.py: 106 bytes a sample, at most
10 million) and written a batch at a time, so memory stays near the table's size, however the input compresses.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from hmdrt.errors import ConfigError
from hmdrt.replay import bids, load_trace
from hmdrt.replay.formats.eyelink import Screen
from hmdrt.replay.formats.generic_csv import write_generic_csv
from hmdrt.replay.table import GAZE, NO_TIME, SampleTable
from hmdrt.replay.trace import TraceReading, write_trace

log = logging.getLogger(__name__)
NATIVE, CSV, BIDS = "native", "hmdrt CSV", "BIDS eye-tracking"
READER_OPTIONS = {  # the readers' options (load_trace's), as hmdrt convert offers them: name: what it is
    "screen_width_mm": f"EyeLink: the screen's width in mm (default {Screen.width_mm:g})",
    "screen_height_mm": f"EyeLink: the screen's height in mm (default {Screen.height_mm:g})",
    "distance_mm": f"EyeLink: the eye's distance from the screen in mm (default {Screen.distance_mm:g})",
    "min_confidence": "Pupil Player: rows below this confidence are invalid (default 0.6)",
}
OUTPUTS = {bids.SUFFIX: BIDS, ".jsonl": NATIVE, ".jsonl.gz": NATIVE, ".csv": CSV, ".csv.gz": CSV}  # name ending: format


@dataclass
class Conversion:
    """What a conversion read and wrote."""

    reading: TraceReading
    output_format: str
    written: list[Path]
    samples: int  # samples written
    left_out: int  # samples the output format does not hold (head poses in a gaze-only format)


def output_format(out: str | Path) -> str:
    """The format OUT's name asks for; a ConfigError naming the ones hmdrt writes."""
    name = Path(out).name.lower()
    kind = next((kind for ending, kind in OUTPUTS.items() if name.endswith(ending)), None)
    if kind is None:
        endings = {kind: " or ".join(e for e, k in OUTPUTS.items() if k == kind) for kind in OUTPUTS.values()}
        writes = ", ".join(f"{kind} ({names})" for kind, names in endings.items())
        raise ConfigError(f"{Path(out).name}: an output's name says its format; hmdrt writes {writes}")
    return kind


def _native(out: Path, reading: TraceReading) -> int:
    write_trace(out, reading.samples, reading.device)
    return len(reading.samples)


def _bids(out: Path, reading: TraceReading) -> int:
    bids.write_physio(out, reading.samples)
    return SampleTable.of(reading.samples).gaze_count


def _device_times(table: SampleTable) -> bool:
    """Whether some gaze sample has a device time other than its t_host."""
    return any(
        ((rows.kind == GAZE) & (rows.t_dev != NO_TIME) & (rows.t_dev != rows.t_host)).any() for rows in table.columns()
    )


WRITERS: dict[str, Callable[[Path, TraceReading], int]] = {  # each returns how many samples it wrote
    NATIVE: _native,
    CSV: lambda out, reading: write_generic_csv(out, reading.samples),
    BIDS: _bids,
}


def convert_trace(source: str | Path, out: str | Path, force: bool = False, **options: float) -> Conversion:
    """Read SOURCE (options go to its format's reader, as load_trace's) and write it to OUT in the format OUT names.

    An existing output is replaced only with force."""
    out = Path(out)
    kind = output_format(out)
    reading = load_trace(source, **options)
    targets = [out]
    if kind == BIDS:
        targets = [path for pair in bids.physio_files(out, reading.samples).values() for path in pair]
    if not force and (existing := [p for p in targets if p.exists()]):
        raise ConfigError(f"{existing[0]} exists; --force replaces it")
    if kind != NATIVE and _device_times(SampleTable.of(reading.samples)):
        log.info("%s: device times (t_dev) left out; %s keeps one time per sample, t_host", out.name, kind)
    samples = WRITERS[kind](out, reading)
    left_out = len(reading.samples) - samples
    if left_out:
        log.info("%s: %d head-pose samples left out (%s holds gaze only)", out.name, left_out, kind)
    return Conversion(reading, kind, targets, samples, left_out)
