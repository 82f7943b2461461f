"""What a method is given of the gaze in `hmdrt eval`, and how far that is from where the eye looks.

A frame's true gaze is its trace's at the frame's photon time (in virtual time, the frame's own time): bands,
crops, flicker and JOD's fixation follow it. The method is given what a tracker reported instead. The tracker
model (hmdrt.tracking) samples the true gaze: a recording's own samples, or the built-in path and a fixed gaze
sampled at the tracker's period. Each sample reaches the compositor's SampleStore latency_ms after it was taken,
and the store estimates the gaze at the photon time from what has arrived: the newest usable sample (prediction
"off", a horizon of 0) or that sample carried on at its fitted velocity up to the compositor's default horizon
(prediction "default", the run config's [prediction]). Before the trace starts the eye rests at its first gaze, as
the held warm-up frames show it, so the tracker has a history by the first frame; where nothing usable has
arrived yet, the method is given the view's centre (where the compositor's fallback ends up).
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hmdrt.bus.messages import Gaze
from hmdrt.compositor.config import Prediction
from hmdrt.compositor.samples import SampleStore
from hmdrt.errors import ConfigError
from hmdrt.foveation import METHODS, MethodChoice
from hmdrt.replay import load_trace
from hmdrt.replay.trace import usable
from hmdrt.spatial import Pose, angle_between, gaze_direction
from hmdrt.tracking.model import FORWARD, GazeSequence, Tracker, sampling_rate_hz
from hmdrt.views import FrameInput, sequence_inputs

if TYPE_CHECKING:
    from hmdrt.evaluate.config import Trace

LEAD_NS = 1_000_000_000  # the tracker runs this long (and the latency) before the trace, the eye at its first gaze
DEVICE = "tracker"
HORIZONS_NS = {"off": 0, "default": round(Prediction().horizon_ms * 1e6)}
CENTRE = np.array(gaze_direction(0.0, 0.0))


@dataclass(frozen=True)
class TraceFrames:
    """A trace's frames: what the eye and head did at each photon time (scored), and the same frames with the gaze
    the method is given (rendered)."""

    true: list[FrameInput]
    seen: list[FrameInput]


def seen_frames(trace: Trace, frames: list[FrameInput], start: Pose, seed: int) -> list[FrameInput]:
    """`frames` (a trace's, from its start) with each eye's gaze as the method is given it: the trace's tracker,
    latency and prediction applied to the true gaze. Seeded by `seed` and the trace's source, so that one
    recording has the same tracker errors at every latency."""
    tracker = trace.tracker_model
    latency = round(trace.latency_ms * 1e6)
    truth = true_gaze(trace, frames, start, seed, tracker, latency + LEAD_NS)
    reported = tracker.report(truth, (seed, zlib.crc32(_source(trace).encode())))
    samples = [
        Gaze(seq=k, t_host=int(t), L=tuple(left), R=tuple(right)) if ok else Gaze(seq=k, t_host=int(t), valid=False)
        for k, (t, left, right, ok) in enumerate(
            zip(reported.t_ns, reported.left, reported.right, reported.valid, strict=True)
        )
    ]
    store = SampleStore(horizon_ns=HORIZONS_NS[trace.prediction])
    seen, k = [], 0
    for inp in frames:
        photon = inp.t_ns - frames[0].t_ns
        while k < len(samples) and samples[k].t_host + latency <= photon:
            store.add(DEVICE, samples[k], samples[k].t_host + latency)
            k += 1
        estimate = store.gaze_at(photon, photon, DEVICE)
        if estimate is None:
            gaze = {"left": CENTRE, "right": CENTRE}
        elif estimate.predicted_ns == 0:  # a reported sample as it is: the store's copy is re-normalised
            gaze = {"left": reported.left[estimate.source_seq], "right": reported.right[estimate.source_seq]}
        else:
            gaze = {"left": estimate.left, "right": estimate.right}
        seen.append(dataclasses.replace(inp, gaze=gaze))
    return seen


def true_gaze(
    trace: Trace, frames: list[FrameInput], start: Pose, seed: int, tracker: Tracker, lead_ns: int
) -> GazeSequence:
    """The gaze the tracker samples, in ns from the trace's start (its first frame), from lead_ns before it (the eye
    at its first frame's gaze): a recording's samples; the built-in path or a fixed gaze at the tracker's period,
    or at the frames' times for a tracker reporting every sample."""
    first = frames[0].gaze
    rows = [(-lead_ns, first["left"], first["right"], True)]
    if trace.path:
        rows += _recording_rows(trace.path)
    elif tracker.period_ns is None:
        rows += [(inp.t_ns - frames[0].t_ns, inp.gaze["left"], inp.gaze["right"], True) for inp in frames]
    else:
        count = (frames[-1].t_ns - frames[0].t_ns) // tracker.period_ns + 1
        grid = sequence_inputs(start, tracker.period_ns, count, trace.source, trace.gaze or "0,0", seed)[0]
        rows += [(inp.t_ns, inp.gaze["left"], inp.gaze["right"], True) for inp in grid]
    t, left, right, valid = zip(*rows, strict=True)
    return GazeSequence(np.array(t, dtype=np.int64), np.array(left), np.array(right), np.array(valid))


def _recording_rows(path: str) -> list[tuple]:
    """A recording's gaze samples as (t_ns from its start, left, right, usable), its start as from_trace takes it:
    the first gaze or pose sample."""
    samples = sorted(load_trace(path).samples, key=lambda s: s.t_host)
    gazes = [s for s in samples if isinstance(s, Gaze)]
    t0 = samples[0].t_host if samples else 0
    return [(s.t_host - t0, *(s.eye_directions() if usable(s) else (FORWARD, FORWARD)), usable(s)) for s in gazes]


def check_rates(traces: list[Trace], source: str | Path) -> None:
    """A ConfigError naming the config file `source`, before anything is rendered, for a trace whose tracker samples
    faster than its recording."""
    for i, trace in enumerate(traces):
        tracker = trace.tracker_model
        if trace.path and tracker.period_ns is not None:
            rate = sampling_rate_hz(np.array([row[0] for row in _recording_rows(trace.path)], dtype=np.int64))
            try:
                tracker.check_rate(rate, f"the recording {Path(trace.path).name}")
            except ValueError as exc:
                raise ConfigError(f"{source}: traces[{i}].tracker ({trace.tracker_label}): {exc}") from None


def _source(trace: Trace) -> str:
    """What the trace replays, named the same wherever it is read from: a recording's file name, the built-in path
    or the fixed gaze."""
    return f"path {Path(trace.path).name}" if trace.path else "builtin" if trace.builtin else f"gaze {trace.gaze}"


def gaze_errors_deg(true: list[FrameInput], seen: list[FrameInput], eye: str) -> np.ndarray:
    """The angle (degrees) between the gaze each frame was rendered for and the true gaze, frame by frame."""
    return np.degrees([angle_between(s.gaze[eye], t.gaze[eye]) for t, s in zip(true, seen, strict=True)])


def foveal_radius_deg(choice: MethodChoice) -> float | None:
    """The method's foveal radius at this setting: the first knob it declares foveal (Knob.foveal: weier16's and
    weier18's r0, rrm's fovea_deg, kim21's e_f); None for a method without a fovea (full, regular)."""
    method = METHODS[choice.name]
    knob = next((k for k in method.knobs if k.foveal), None)
    return None if knob is None else float(method.knob_values(choice.params)[knob.field])


def gaze_columns(trace: Trace, errors: np.ndarray) -> dict:
    """A group's gaze columns: the latency, tracker and prediction, and the gaze error at photon time over its
    scored frames (median and 95th percentile, degrees)."""
    return {
        "latency_ms": trace.latency_ms,
        "tracker": trace.tracker_label,
        "prediction": trace.prediction,
        "gaze_error_p50_deg": round(float(np.percentile(errors, 50)), 5),
        "gaze_error_p95_deg": round(float(np.percentile(errors, 95)), 5),
    }


def outside_fovea(errors: np.ndarray, radius: float | None) -> float | None:
    """The share of the scored frames whose gaze error exceeds the foveal radius (None: the method has none)."""
    return None if radius is None else round(float(np.mean(errors > radius)), 5)
