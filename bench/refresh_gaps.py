"""How long rrm's peripheral pixels wait between refreshes in a run whose refresh cycle the budget controller moved.

    python bench/refresh_gaps.py FRAMES.jsonl [FRAMES.jsonl ...]

smith2013's refresh rate modulation (section 3.2.1) refreshes each peripheral pixel once every N = group_w x group_h
frames; the user study (section 4) found N up to 20 unnoticed. A change of N regroups the cells, so a pixel can
wait longer across changes, and the controller (foresight above all) changes N as the gaze lands on costly content
and leaves it. For each frames log of an rrm run (`hmdrt run ... --frames-log FRAMES.jsonl`), this replays rrm's
schedule (hmdrt.foveation.stages.refresh.RefreshSchedule) on the parameters each shown frame was rendered with, or
with --fixed the schedule of a fixed N (frame mod N, rrm's until 12-06), and prints how often N changed and, over
the pixels of one eye at the profile's size (the schedule repeats every group_h rows and block x group_w columns,
so the size barely matters), the longest wait between two scheduled refreshes: p50, p99 and max, in frames.
Refreshes by the foveal rectangle are not counted, so the waits are an upper bound. A frame rendered but never
shown (the report's `dropped`) is not in the log, so after one the replay can differ from the run by a cell.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import msgspec
import numpy as np

# bench/drivers.py shares the drivers package's name: keep this folder from shadowing the package
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != Path(__file__).resolve().parent]

from hmdrt.errors import HmdrtError  # noqa: E402
from hmdrt.foveation.rrm import RrmParams  # noqa: E402
from hmdrt.foveation.stages.refresh import RefreshSchedule, refresh_phase  # noqa: E402
from hmdrt.optics import get_profile  # noqa: E402
from hmdrt.telemetry.frames_log import read_frames_log  # noqa: E402


def gaps(path: str, fixed: bool = False) -> str:
    """One log's line: frames, changes of N, and the longest scheduled wait per pixel (p50, p99, max)."""
    reading = read_frames_log(path)
    if reading.header.method.split("?")[0] != "rrm":
        raise HmdrtError(f"a run of {reading.header.method}, not rrm")
    profile = get_profile(reading.header.profile)
    shape = (profile.height, profile.width)
    last, longest = np.full(shape, -1, np.int64), np.zeros(shape, np.int64)
    phases: dict[RrmParams, np.ndarray] = {}
    frames = changes = 0
    rrm = RefreshSchedule()
    before = None
    for record in reading.records:
        if record.shown == "repeat":
            continue
        cycle = {k: v for k, v in record.params.items() if k in ("group_w", "group_h", "block", "order")}
        p = msgspec.convert(cycle, RrmParams)
        if p not in phases:
            phases[p] = refresh_phase(profile.width, profile.height, p)
        phase = record.frame_id % p.cycle if fixed else rrm.phase(record.frame_id, profile.width, p)
        refreshed = phases[p] == phase
        waited = refreshed & (last >= 0)
        longest[waited] = np.maximum(longest[waited], record.frame_id - last[waited])
        last[refreshed] = record.frame_id
        changes += before is not None and p.cycle != before.cycle
        frames, before = frames + 1, p
    if not frames:
        raise HmdrtError("no frame rendered")
    waits = longest[last >= 0]
    return (
        f"{path}: {frames} frames, N changed {changes} times; the longest wait between a peripheral pixel's "
        f"refreshes p50 {np.median(waits):.0f}, p99 {np.percentile(waits, 99):.0f}, max {waits.max()} frames; "
        f"{int((last < 0).sum())} pixels never refreshed"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("logs", nargs="+", help="frames logs of rrm runs")
    ap.add_argument("--fixed", action="store_true", help="replay frame mod N instead of rrm's schedule")
    args = ap.parse_args()
    for path in args.logs:
        try:
            print(gaps(path, args.fixed))
        except (HmdrtError, msgspec.ValidationError) as exc:
            message = str(exc)  # read_frames_log's errors name the file already
            print(message if path in message else f"{path}: {message}", file=sys.stderr)
            sys.exit(2)


if __name__ == "__main__":
    main()
