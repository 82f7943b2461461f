"""What a method is given of the gaze and the head pose in `hmdrt eval`, and how far that is from the truth.

A frame's true gaze and head pose are its trace's at the frame's photon time (in virtual time, the frame's own
time): bands, crops, flicker and JOD's fixation follow the true gaze, and the ground truths are rendered at the
true pose. The method is given what the trackers reported instead. The eye tracker model (hmdrt.tracking.model)
samples the true gaze: a recording's own samples, or the built-in path and a fixed gaze sampled at the tracker's
period. The head tracker model (hmdrt.tracking.pose) samples the true pose alike: a recording's pose samples, or
at its period the built-in path's head sway or a still head (a fixed gaze, or a recording without poses). Each
gaze sample reaches the compositor's SampleStore latency_ms after it was taken, each pose sample pose_latency_ms
after, and the store estimates both at the photon time from what has arrived: the newest usable sample
(prediction "off", a horizon of 0) or that sample carried on at its fitted velocity up to the compositor's default
horizon (prediction "default", the run config's [prediction]), turning along a predicted saccade's flight to its
landing point where the saccade predictor has one (prediction "saccade", as with [gaze] saccade_prediction).
Before the trace starts the eye and head rest as at its first frame, as the held warm-up frames show them, so the
trackers have a history by the first frame; where no usable gaze has arrived yet, the method is given the view's
centre (where the compositor's fallback ends up).
"""

from __future__ import annotations

import dataclasses
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hmdrt.bus.messages import Gaze
from hmdrt.bus.messages import Pose as PoseSample
from hmdrt.compositor.config import Prediction
from hmdrt.compositor.samples import GazeEstimate, PoseEstimate, SampleStore
from hmdrt.errors import ConfigError
from hmdrt.foveation import METHODS, MethodChoice
from hmdrt.replay import load_trace
from hmdrt.replay.trace import usable
from hmdrt.spatial import Pose, angle_between, gaze_direction, norm, quat_conjugate, quat_multiply, quat_to_rotvec
from hmdrt.tracking.model import FORWARD, GazeSequence, Sampling, Tracker, sampling_rate_hz
from hmdrt.tracking.pose import PoseSequence, PoseTracker
from hmdrt.views import FrameInput, compose_pose, sequence_inputs

if TYPE_CHECKING:
    from hmdrt.evaluate.config import Trace

LEAD_NS = 1_000_000_000  # the trackers run this long (and their latency) before the trace, eye and head at rest
DEVICE = "tracker"
HORIZON_NS = round(Prediction().horizon_ms * 1e6)
HORIZONS_NS = {"off": 0, "default": HORIZON_NS, "saccade": HORIZON_NS}
CENTRE = np.array(gaze_direction(0.0, 0.0))
POSE_STREAM = 1  # the head tracker's errors come from a random stream of their own, apart from the eye tracker's


@dataclass(frozen=True)
class TraceFrames:
    """A trace's frames: what the eye and head did at each photon time (scored), and the same frames with the gaze
    and pose the method is given (rendered)."""

    true: list[FrameInput]
    seen: list[FrameInput]


def seen_frames(trace: Trace, frames: list[FrameInput], start: Pose, seed: int) -> list[FrameInput]:
    """`frames` (a trace's, from its start) with each eye's gaze and the head pose as the method is given them: the
    trace's trackers, latencies and prediction applied to the true gaze and pose. Seeded by `seed` and the trace's
    source, so that one recording has the same tracker errors at every latency."""
    tracker, pose_tracker = trace.tracker_model, trace.pose_tracker_model
    latency, pose_latency = round(trace.latency_ms * 1e6), round(trace.pose_latency_ms * 1e6)
    salt = (seed, zlib.crc32(_source(trace).encode()))
    gazes = tracker.report(true_gaze(trace, frames, start, seed, tracker, latency + LEAD_NS), salt)
    poses = pose_tracker.report(
        true_pose(trace, frames, start, seed, pose_tracker, pose_latency + LEAD_NS), (*salt, POSE_STREAM)
    )
    arrivals = sorted(
        [
            *((s.t_host + latency, s) for s in _gaze_samples(gazes)),
            *((s.t_host + pose_latency, s) for s in _pose_samples(poses)),
        ],
        key=lambda arrival: arrival[0],
    )
    store = SampleStore(horizon_ns=HORIZONS_NS[trace.prediction], saccades=trace.prediction == "saccade")
    seen, k = [], 0
    for inp in frames:
        photon = inp.t_ns - frames[0].t_ns
        while k < len(arrivals) and arrivals[k][0] <= photon:
            store.add(DEVICE, arrivals[k][1], arrivals[k][0])
            k += 1
        gaze = _gaze_given(store.gaze_at(photon, photon, DEVICE), gazes)
        pose = _pose_given(store.pose_at(photon, photon, DEVICE), poses)
        seen.append(dataclasses.replace(inp, gaze=gaze, pose=pose))
    return seen


def _gaze_samples(reported: GazeSequence) -> list[Gaze]:
    """The reported gaze as the bus carries it, numbered in order (seq: the index into `reported`)."""
    rows = zip(reported.t_ns, reported.left, reported.right, reported.valid, strict=True)
    return [
        Gaze(seq=k, t_host=int(t), L=tuple(left), R=tuple(right)) if ok else Gaze(seq=k, t_host=int(t), valid=False)
        for k, (t, left, right, ok) in enumerate(rows)
    ]


def _pose_samples(reported: PoseSequence) -> list[PoseSample]:
    """The reported head pose as the bus carries it, numbered in order (seq: the index into `reported`)."""
    rows = zip(reported.t_ns, reported.position, reported.orientation, reported.valid, strict=True)
    return [
        PoseSample(seq=k, t_host=int(t), position=tuple(p), orientation=tuple(q), valid=bool(ok))
        for k, (t, p, q, ok) in enumerate(rows)
    ]


def _gaze_given(estimate: GazeEstimate | None, reported: GazeSequence) -> dict[str, np.ndarray]:
    """The gaze the method is given: the view's centre where nothing usable has arrived, a reported sample as it is
    (the store's copy is re-normalised), or the store's prediction from one."""
    if estimate is None:
        return {"left": CENTRE, "right": CENTRE}
    if estimate.predicted_ns == 0:
        return {"left": reported.left[estimate.source_seq], "right": reported.right[estimate.source_seq]}
    return {"left": estimate.left, "right": estimate.right}


def _pose_given(estimate: PoseEstimate, reported: PoseSequence) -> Pose:
    """The head pose the method is given: a reported sample as it is (the store's copy is re-normalised), or the
    store's prediction from one. There is always one: the head at rest was reported before the first frame, and no
    head tracker loses samples."""
    if estimate.predicted_ns == 0:
        return Pose(reported.position[estimate.source_seq], reported.orientation[estimate.source_seq])
    return Pose(estimate.position, estimate.orientation)


def true_gaze(
    trace: Trace, frames: list[FrameInput], start: Pose, seed: int, tracker: Tracker, lead_ns: int
) -> GazeSequence:
    """The gaze the tracker samples, in ns from the trace's start (its first frame), from lead_ns before it (the eye
    at its first frame's gaze): a recording's samples, else the built-in path or a fixed gaze (_sampled)."""
    first = frames[0].gaze
    rows = [(-lead_ns, first["left"], first["right"], True)]
    if trace.path:
        rows += _recorded_gaze(trace.path)
    else:
        rows += [
            (inp.t_ns, inp.gaze["left"], inp.gaze["right"], True)
            for inp in _sampled(trace, frames, start, seed, tracker)
        ]
    t, left, right, valid = zip(*rows, strict=True)
    return GazeSequence(np.array(t, dtype=np.int64), np.array(left), np.array(right), np.array(valid))


def true_pose(
    trace: Trace, frames: list[FrameInput], start: Pose, seed: int, tracker: PoseTracker, lead_ns: int
) -> PoseSequence:
    """The head pose the head tracker samples, in ns from the trace's start (its first frame), from lead_ns before
    it (the head at its first frame's pose): a recording's pose samples, else the built-in path's head or a still
    one (_sampled)."""
    rows = [(-lead_ns, frames[0].pose, True)]
    recorded = _recorded_poses(trace.path, start) if trace.path else []
    rows += recorded or [(inp.t_ns, inp.pose, True) for inp in _sampled(trace, frames, start, seed, tracker)]
    t, poses, valid = zip(*rows, strict=True)
    position, orientation = np.array([p.position for p in poses]), np.array([p.orientation for p in poses])
    return PoseSequence(np.array(t, dtype=np.int64), position, orientation, np.array(valid))


def _sampled(trace: Trace, frames: list[FrameInput], start: Pose, seed: int, tracker: Sampling) -> list[FrameInput]:
    """What the eye and head do where no recording says (the built-in path, else a fixed gaze with the head still),
    in ns from the trace's start: at the frames' own times for a tracker reporting every sample, else at the
    multiples of the tracker's period over the frames' span."""
    if tracker.period_ns is None:
        return [dataclasses.replace(inp, t_ns=inp.t_ns - frames[0].t_ns) for inp in frames]
    count = (frames[-1].t_ns - frames[0].t_ns) // tracker.period_ns + 1
    source = "builtin" if trace.builtin else None
    return sequence_inputs(start, tracker.period_ns, count, source, trace.gaze or "0,0", seed)[0]


def _recording(path: str, kind: type) -> tuple[list, int]:
    """A recording's samples of one kind (Gaze or PoseSample) in time order, and its start as from_trace takes it:
    the first gaze or pose sample's time."""
    samples = sorted(load_trace(path).samples, key=lambda s: s.t_host)
    return [s for s in samples if isinstance(s, kind)], samples[0].t_host if samples else 0


def _recorded_gaze(path: str) -> list[tuple]:
    """A recording's gaze samples as (t_ns from its start, left, right, usable)."""
    gazes, t0 = _recording(path, Gaze)
    return [(s.t_host - t0, *(s.eye_directions() if usable(s) else (FORWARD, FORWARD)), usable(s)) for s in gazes]


def _recorded_poses(path: str, start: Pose) -> list[tuple]:
    """A recording's pose samples as (t_ns from its start, the head pose placed at `start` as from_trace places it,
    usable); an unusable one holds `start`, which means nothing."""
    poses, t0 = _recording(path, PoseSample)
    return [(s.t_host - t0, compose_pose(start, s) if usable(s) else start, usable(s)) for s in poses]


def check_rates(traces: list[Trace], source: str | Path) -> None:
    """A ConfigError naming the config file `source`, before anything is rendered, for a trace whose eye or head
    tracker samples faster than its recording's gaze or poses."""
    for i, trace in enumerate(traces):
        checks = (
            ("tracker", trace.tracker_model, trace.tracker_label, Gaze),
            ("pose_tracker", trace.pose_tracker_model, trace.pose_tracker_label, PoseSample),
        )
        for key, tracker, label, kind in checks:
            if trace.path and tracker.period_ns is not None:
                rate = sampling_rate_hz(np.array([s.t_host for s in _recording(trace.path, kind)[0]], dtype=np.int64))
                try:
                    tracker.check_rate(rate, f"the recording {Path(trace.path).name}")
                except ValueError as exc:
                    raise ConfigError(f"{source}: traces[{i}].{key} ({label}): {exc}") from None


def _source(trace: Trace) -> str:
    """What the trace replays, named the same wherever it is read from: a recording's file name, the built-in path
    or the fixed gaze."""
    return f"path {Path(trace.path).name}" if trace.path else "builtin" if trace.builtin else f"gaze {trace.gaze}"


def gaze_errors_deg(true: list[FrameInput], seen: list[FrameInput], eye: str) -> np.ndarray:
    """The angle (degrees) between the gaze each frame was rendered for and the true gaze, frame by frame."""
    return np.degrees([angle_between(s.gaze[eye], t.gaze[eye]) for t, s in zip(true, seen, strict=True)])


def pose_errors_deg(true: list[FrameInput], seen: list[FrameInput]) -> np.ndarray:
    """The angle (degrees) of the rotation between the head orientation each frame was rendered for and the true
    one, frame by frame."""
    turns = (
        quat_multiply(s.pose.orientation, quat_conjugate(t.pose.orientation)) for t, s in zip(true, seen, strict=True)
    )
    return np.degrees([norm(quat_to_rotvec(turn)) for turn in turns])


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
        **_percentiles("gaze_error", errors),
    }


def pose_columns(trace: Trace, errors: np.ndarray) -> dict:
    """A group's pose columns: the pose latency and tracker, and the head orientation error at photon time over its
    scored frames (median and 95th percentile, degrees)."""
    return {
        "pose_latency_ms": trace.pose_latency_ms,
        "pose_tracker": trace.pose_tracker_label,
        **_percentiles("pose_error", errors),
    }


def _percentiles(name: str, errors: np.ndarray) -> dict[str, float]:
    """The median and 95th percentile of errors in degrees, as NAME_p50_deg and NAME_p95_deg."""
    return {f"{name}_p{q}_deg": round(float(np.percentile(errors, q)), 5) for q in (50, 95)}


def outside_fovea(errors: np.ndarray, radius: float | None) -> float | None:
    """The share of the scored frames whose gaze error exceeds the foveal radius (None: the method has none)."""
    return None if radius is None else round(float(np.mean(errors > radius)), 5)
