"""Recorded and synthetic gaze and head-pose traces."""

from __future__ import annotations

import inspect
from pathlib import Path

from hmdrt.errors import ConfigError
from hmdrt.replay.formats import (
    csv_header,
    eyelink,
    gazebase,
    gazebase_desktop,
    generic_csv,
    pupil_player,
    refuse_columns,
)
from hmdrt.replay.trace import TraceReading, read_trace

SUPPORTED = (
    "native hmdrt traces (.jsonl, .jsonl.gz), EyeLink ASC (.asc), and CSV (.csv) from GazeBase, GazeBaseVR, "
    "Pupil Player gaze_positions or hmdrt's t_ns/t_ms/t_s schema"
)
CSV_READERS = (  # tried in this order; each format's module declares its NAME, NEEDS and matches()
    (pupil_player, pupil_player.read_pupil_player),
    (gazebase, gazebase.read_gazebase),
    (gazebase_desktop, gazebase_desktop.read_gazebase_desktop),
    (generic_csv, generic_csv.read_generic_csv),
)


def load_trace(path: str | Path, **options) -> TraceReading:
    """A trace file as normalised samples, its format chosen by extension (and a CSV's header row).

    options go to the format's reader, e.g. screen_width_mm, screen_height_mm, distance_mm for
    EyeLink or min_confidence for Pupil Player; one the format does not take is a ConfigError.
    """
    path = Path(path)
    name = path.name.lower().removesuffix(".gz")
    reader = None
    if name.endswith(".jsonl"):
        reader = read_trace
    elif name.endswith(".asc"):
        reader = eyelink.read_asc
    elif name.endswith(".csv"):
        header = csv_header(path)
        reader = next((read for form, read in CSV_READERS if form.matches(header)), None)
        if reader is None:
            raise refuse_columns(path, header, {form.NAME: form.NEEDS for form, _ in CSV_READERS})
    if reader is None:
        raise ConfigError(f"{path} is not a trace format hmdrt reads; it reads {SUPPORTED}")
    known = inspect.signature(reader).parameters
    if unknown := sorted(set(options) - set(known)):
        raise ConfigError(
            f"{path.name} takes no option {unknown[0]!r}; options: {', '.join(list(known)[1:]) or 'none'}"
        )
    return reader(path, **options)
