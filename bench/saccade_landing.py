"""Saccade landing prediction against no prediction and linear extrapolation, by saccade amplitude.

python bench/saccade_landing.py [--cili DIR] [--synthetic] [--latency-ms 20 35 50]

Saccades: those a recording's EyeLink parser marked (its ESACC lines: eye, start, end) with no invalid sample from
5 ms before the start to the end (one that runs into a blink, like raccoons.asc's, has no recorded landing); with
--synthetic also hmdrt's synthetic ones (replay.synthetic: minimum-jerk profiles over Carpenter's main-sequence
durations) of 2-30 deg at 250 and 1000 Hz with 0.03 deg of noise. The samples go to the compositor's SampleStore
as they arrive. For each saccade and latency L:

- in flight: each sample from the saccade's start to its end is in turn the newest a frame knows, and the frame
  is shown L later; the error is the angle between the estimate for then and the recorded gaze then (the first
  sample at or after it), averaged over the saccade's samples;
- landing frame: the frame shown when the saccade ends, made from the newest sample L before; the error is the
  angle between its estimate and the recorded gaze at the end.

Estimates: none (the newest sample held), linear (SampleStore: the velocity of the newest 3 samples within 25 ms
extrapolated, at most 50 ms) and saccade (SampleStore(saccades=True), as `[gaze] saccade_prediction = true`:
the predicted flight where there is one, else linear). The tables give each error averaged over the saccades of
an amplitude bin (their recorded start-to-end angle), then the share of saccades predicted, when the first
prediction came (median ms after the start) and its landing error (median % of the amplitude).

Recordings: tests/data/traces/eyelink_mono1000_saccades.asc (4 prosaccades of 7.4-8 deg at 1000 Hz), or with
--cili DIR the EyeLink recordings of https://github.com/beOn/cili (tests/data at commit
ecfcb09452136e36d82ed0b4eae4150fbfec239a, BSD 3-clause): mono and bino at 250, 500, 1000 and 2000 Hz (prosaccades of
6-8 deg) and monoRemote500 (reading at 500 Hz: 296 saccades of 0.3-22 deg). They are read as a 400 x 300 mm screen at
785 mm, which gives their recorded resolution (RES 35.1 px/deg on the END lines) at the centre. To get them:
fetch github:beOn/cili, then for each NAME.asc `git -C MIRROR show ecfcb094:tests/data/NAME.asc > DIR/NAME.asc`.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hmdrt.bus.messages import Gaze
from hmdrt.compositor.samples import SampleStore
from hmdrt.replay import load_trace
from hmdrt.replay.synthetic import minimum_jerk, saccade_duration_s
from hmdrt.spatial import Vec, angle_between, gaze_direction
from hmdrt.tracking.saccade import SaccadePredictor

MS = 1_000_000
TRACES = Path(__file__).resolve().parents[1] / "tests" / "data" / "traces"
CILI_SCREEN = {"screen_width_mm": 400.0, "screen_height_mm": 300.0, "distance_mm": 785.0}
CILI = ("mono250", "mono500", "mono1000", "mono2000", "bino250", "bino500", "bino1000", "monoRemote500")
BINS = ((0.0, 2.0), (2.0, 5.0), (5.0, 10.0), (10.0, 30.0))
METHODS = ("none", "linear", "saccade")
SYNTHETIC = (2.0, 3.0, 4.0, 6.0, 8.0, 10.0, 12.0, 15.0, 20.0, 25.0, 30.0)  # amplitudes, degrees


@dataclass
class Saccade:
    """One saccade's errors (degrees) by (measure, method, latency ms), and its first prediction."""

    amplitude_deg: float
    errors: dict[tuple[str, str, int], float] = field(default_factory=dict)
    first_ms: float | None = None  # after the start
    first_error: float | None = None  # its landing error, % of the amplitude


@dataclass
class Stream:
    """One eye's samples (unit gaze, None when invalid) and its marked saccades (first and last index)."""

    name: str
    times: list[int]
    gazes: list[Vec | None]
    marked: list[tuple[int, int]]


def recordings(cili: Path | None) -> Iterator[Stream]:
    """The recordings' eye streams: cili's whole recordings with --cili, else the excerpt of mono1000 in tests."""
    paths = [cili / f"{name}.asc" for name in CILI] if cili else [TRACES / "eyelink_mono1000_saccades.asc"]
    for path in paths:
        samples = load_trace(path, **CILI_SCREEN).samples
        times = [s.t_host for s in samples]
        marked: dict[str, list[tuple[int, int]]] = {}
        for line in path.read_text(errors="replace").splitlines():
            fields = line.split()
            if fields[:1] == ["ESACC"] and len(fields) > 3:
                start, end = int(fields[2]) * MS, int(fields[3]) * MS
                span = (int(np.searchsorted(times, start - 5 * MS)), int(np.searchsorted(times, end, "right")) - 1)
                if all(samples[k].valid for k in range(*span)) and samples[span[1]].valid:
                    marked.setdefault(fields[1], []).append((int(np.searchsorted(times, start)), span[1]))
        for eye, spans in marked.items():
            gazes = [getattr(s, eye) if s.valid else None for s in samples]
            yield Stream(f"{path.name} {eye}", times, gazes, spans)


def synthetic() -> Iterator[Stream]:
    """hmdrt's synthetic saccades, one stream per rate: three of each amplitude in seeded random directions (kept
    within 30 deg of straight ahead), 300 ms of fixation between them."""
    rng = np.random.default_rng(0)
    for rate in (250, 1000):
        times: list[int] = []
        gazes: list[Vec | None] = []
        marked = []
        here = np.zeros(2)  # yaw, pitch
        for amplitude in SYNTHETIC * 3:
            heading = rng.uniform(0.0, 2.0 * math.pi)
            step = amplitude * np.array([math.cos(heading), math.sin(heading)])
            step = -step if np.abs(here + step).max() > 30.0 else step
            duration, begin = saccade_duration_s(amplitude), len(times)
            for t in np.arange(0.0, 0.3 + duration, 1.0 / rate):
                point = here + step * minimum_jerk((t - 0.2) / duration) + rng.normal(0.0, 0.03, 2)
                times.append(round(len(times) * 1e9 / rate))
                gazes.append(gaze_direction(*point))
            marked.append((begin + math.ceil(0.2 * rate), begin + math.ceil((0.2 + duration) * rate)))
            here = here + step
        yield Stream(f"synthetic {rate} Hz", times, gazes, marked)


def measure(stream: Stream, latencies: list[int]) -> list[Saccade]:
    times, gazes = stream.times, stream.gazes
    queries: dict[int, list[int]] = {}  # sample index -> display times to estimate when it is the newest
    for start, end in stream.marked:
        for latency in latencies:
            for k in range(start, end + 1):
                queries.setdefault(k, []).append(times[k] + latency * MS)
            newest = int(np.searchsorted(times, times[end] - latency * MS, "right")) - 1
            queries.setdefault(newest, []).append(times[end])
    stores = {"linear": SampleStore(), "saccade": SampleStore(saccades=True)}
    predictor = SaccadePredictor()
    estimates: dict[tuple[str, int, int], Vec] = {}
    predicted: dict[int, Vec] = {}  # sample index -> the landing predicted there
    for k, (t, g) in enumerate(zip(times, gazes, strict=True)):
        for store in stores.values():
            store.add("eye", Gaze(seq=k, t_host=t, valid=g is not None, L=g), t)
        flight = predictor.update(t, g)
        if flight is not None:
            predicted[k] = flight.landing
        for shown in queries.get(k, ()):
            if g is None:
                continue
            estimates[("none", k, shown)] = g
            for name, store in stores.items():
                estimates[(name, k, shown)] = tuple(store.gaze_at(shown, t, "eye").left)
    out = []
    for start, end in stream.marked:
        saccade = Saccade(math.degrees(angle_between(gazes[start], gazes[end])))
        for latency in latencies:
            for method in METHODS:
                errors = []
                for k in range(start, end + 1):
                    j = int(np.searchsorted(times, times[k] + latency * MS))
                    if j < len(times) and gazes[j] is not None and (method, k, times[k] + latency * MS) in estimates:
                        errors.append(angle_between(estimates[(method, k, times[k] + latency * MS)], gazes[j]))
                saccade.errors[("in flight", method, latency)] = math.degrees(float(np.mean(errors)))
                newest = int(np.searchsorted(times, times[end] - latency * MS, "right")) - 1
                landing = estimates.get((method, newest, times[end]))
                if landing is not None:
                    saccade.errors[("landing", method, latency)] = math.degrees(angle_between(landing, gazes[end]))
        first = next((k for k in range(start, end + 1) if k in predicted), None)
        if first is not None:
            saccade.first_ms = (times[first] - times[start]) / MS
            saccade.first_error = (
                100.0 * math.degrees(angle_between(predicted[first], gazes[end])) / saccade.amplitude_deg
            )
        out.append(saccade)
    return out


def table(title: str, saccades: list[Saccade], latencies: list[int]) -> str:
    head = f"{'amplitude':>10} {'n':>4} " + " ".join(f"{m[:6]}@{L}".rjust(11) for L in latencies for m in METHODS)
    lines = [title, "", "measure: in flight | landing frame (degrees, mean over the bin's saccades)", head]
    for low, high in BINS:
        chosen = [s for s in saccades if low <= s.amplitude_deg < high]
        if not chosen:
            continue
        cells = []
        for latency in latencies:
            for method in METHODS:
                flight = np.mean([s.errors[("in flight", method, latency)] for s in chosen])
                landed = [
                    s.errors[("landing", method, latency)] for s in chosen if ("landing", method, latency) in s.errors
                ]
                cells.append(f"{flight:5.2f}|{np.mean(landed):5.2f}")
        lines.append(f"{f'{low:g}-{high:g} deg':>10} {len(chosen):4d} " + " ".join(c.rjust(11) for c in cells))
    lines += ["", f"{'amplitude':>10} {'n':>4} {'predicted':>10} {'first ms':>9} {'first err %':>12}"]
    for low, high in BINS:
        chosen = [s for s in saccades if low <= s.amplitude_deg < high]
        if not chosen:
            continue
        hits = [s for s in chosen if s.first_ms is not None]
        first = f"{np.median([s.first_ms for s in hits]):9.0f}" if hits else f"{'-':>9}"
        error = f"{np.median([s.first_error for s in hits]):12.1f}" if hits else f"{'-':>12}"
        share = f"{100 * len(hits) / len(chosen):9.0f}%"
        lines.append(f"{f'{low:g}-{high:g} deg':>10} {len(chosen):4d} {share} {first} {error}")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cili", type=Path, help="a folder with cili's tests/data recordings (mono1000.asc, ...)")
    parser.add_argument("--synthetic", action="store_true", help="also hmdrt's synthetic main-sequence saccades")
    parser.add_argument("--latency-ms", type=int, nargs="+", default=[20, 35, 50])
    args = parser.parse_args()
    recorded = [s for stream in recordings(args.cili) for s in measure(stream, args.latency_ms)]
    print(table(f"Recorded saccades: {len(recorded)}", recorded, args.latency_ms))
    if args.synthetic:
        made = [s for stream in synthetic() for s in measure(stream, args.latency_ms)]
        print()
        print(table(f"Synthetic saccades: {len(made)}", made, args.latency_ms))


if __name__ == "__main__":
    main()
