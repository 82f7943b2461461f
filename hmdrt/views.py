"""Frame sequences: what each frame sees (head pose, per-eye gaze) from a trace or a built-in path,
and the loop that renders them through a method at the profile's refresh period.

A frame at time t uses the latest usable gaze and pose sample at or before t (invalid samples and
blinks keep the last valid gaze and are counted). Trace poses are relative to the scene's start pose.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from hmdrt.errors import ConfigError
from hmdrt.foveation.base import EYES, FrameRequest, Method
from hmdrt.foveation.stages.gaze import vergence_depth
from hmdrt.optics import EyeCamera, HmdProfile
from hmdrt.replay import load_trace
from hmdrt.replay.trace import Gaze, TraceReading, usable
from hmdrt.replay.trace import Pose as PoseSample
from hmdrt.spatial import Pose, gaze_direction, parse_gaze, quat_multiply, quat_rotate, unit
from hmdrt.telemetry.stats import FrameStats


@dataclass(frozen=True)
class FrameInput:
    """What one frame sees: the head pose in the world and each eye's unit gaze in the head frame."""

    frame: int
    t_ns: int
    pose: Pose
    gaze: dict[str, np.ndarray]
    gaze_depth_m: float | None = None


@dataclass
class SequenceCounts:
    """What a trace-driven sequence did with the trace's samples."""

    gaze_invalid: int = 0
    pose_invalid: int = 0
    held_frames: int = 0  # frames whose gaze was the last valid one because the newest was invalid
    malformed_lines: int = 0


def compose_pose(start: Pose, relative: PoseSample) -> Pose:
    """A head pose relative to where a trace started, placed at the scene's start pose."""
    orientation = quat_multiply(start.orientation, unit(relative.orientation))
    return Pose(start.position + quat_rotate(start.orientation, relative.position), orientation)


def from_trace(
    reading: TraceReading, frames: int, period_ns: int, start: Pose
) -> tuple[list[FrameInput], SequenceCounts]:
    """frames inputs at the refresh period from the trace's first sample time."""
    gazes = sorted((s for s in reading.samples if isinstance(s, Gaze)), key=lambda s: s.t_host)
    poses = sorted((s for s in reading.samples if isinstance(s, PoseSample)), key=lambda s: s.t_host)
    counts = SequenceCounts(malformed_lines=reading.malformed)
    counts.gaze_invalid = sum(not usable(s) for s in gazes)
    counts.pose_invalid = sum(not usable(s) for s in poses)
    valid_gaze = [s for s in gazes if usable(s)]
    if not valid_gaze:
        raise ConfigError("the trace has no valid gaze sample")
    valid_pose = [s for s in poses if usable(s)]
    t0 = min(s.t_host for s in (gazes[0], *poses[:1]))
    inputs, gi, pi, all_i = [], -1, -1, -1
    for f in range(frames):
        t = t0 + f * period_ns
        while gi + 1 < len(valid_gaze) and valid_gaze[gi + 1].t_host <= t:
            gi += 1
        while all_i + 1 < len(gazes) and gazes[all_i + 1].t_host <= t:
            all_i += 1
        while pi + 1 < len(valid_pose) and valid_pose[pi + 1].t_host <= t:
            pi += 1
        sample = valid_gaze[max(gi, 0)]
        counts.held_frames += all_i >= 0 and not usable(gazes[all_i])
        pose = start if pi < 0 else compose_pose(start, valid_pose[pi])
        left, right = sample.eye_directions()
        inputs.append(FrameInput(f, t, pose, {"left": np.array(left), "right": np.array(right)}, sample.depth_m))
    return inputs, counts


def sequence_inputs(
    start: Pose, period_ns: int, frames: int | None, trace: str | None = None, gaze: str = "0,0", seed: int = 0
) -> tuple[list[FrameInput], SequenceCounts | None]:
    """What each frame sees: a fixed gaze with the head still at `start` (trace None), the built-in path
    (trace "builtin"), or a trace file (frames None: as many as the trace spans at the period)."""
    if trace and trace != "builtin":
        reading = load_trace(trace)
        if frames is None:
            times = [s.t_host for s in reading.samples]
            frames = (max(times) - min(times)) // period_ns + 1 if times else 1
        return from_trace(reading, frames, period_ns, start)
    frames = frames or 1
    if trace == "builtin":
        return builtin_path(frames, period_ns, start, seed), None
    g = np.array(gaze_direction(*parse_gaze(gaze)))
    return [FrameInput(f, f * period_ns, start, {"left": g, "right": g}) for f in range(frames)], None


def builtin_path(frames: int, period_ns: int, start: Pose, seed: int = 0) -> list[FrameInput]:
    """A deterministic head path with fixations: the head sways +-6 deg in yaw and +-2 deg in pitch;
    the gaze fixates seeded points within +-15 deg for 250-450 ms each and saccades between them."""
    rng = np.random.default_rng(seed)
    fixations: list[tuple[float, float, float]] = []  # (start time s, yaw, pitch)
    t = 0.0
    end = frames * period_ns * 1e-9
    while t <= end:
        fixations.append((t, *rng.uniform(-15.0, 15.0, size=2)))
        t += rng.uniform(0.25, 0.45)
    inputs = []
    k = 0
    for f in range(frames):
        ts = f * period_ns * 1e-9
        while k + 1 < len(fixations) and fixations[k + 1][0] <= ts:
            k += 1
        _, yaw, pitch = fixations[k]
        sway = Pose.looking((0.0, 0.0, 0.0), 6.0 * math.sin(math.pi * 0.5 * ts), 2.0 * math.sin(math.pi * 0.34 * ts))
        pose = Pose(start.position, quat_multiply(start.orientation, sway.orientation))
        g = np.array(gaze_direction(yaw, pitch))
        inputs.append(FrameInput(f, f * period_ns, pose, {"left": g, "right": g}))
    return inputs


def eye_cameras(profile: HmdProfile, pose: Pose, eyes: tuple[str, ...]) -> dict[str, EyeCamera]:
    rotation = pose.rotation()
    return {eye: EyeCamera.for_eye(profile, pose, eye, rotation) for eye in eyes}


def frame_requests(inp: FrameInput, cameras: dict[str, EyeCamera], seed: int) -> list[FrameRequest]:
    """One request per eye; the gaze depth is the trace's, or the vergence of the two eyes' gaze."""
    depth = inp.gaze_depth_m
    if depth is None and set(EYES) <= set(cameras):
        rot = cameras["left"].rotation
        head_l = rot.T @ (cameras["left"].position - inp.pose.position)
        head_r = rot.T @ (cameras["right"].position - inp.pose.position)
        depth = vergence_depth(head_l, inp.gaze["left"], head_r, inp.gaze["right"])
    return [FrameRequest(cam, inp.gaze[eye], inp.frame, seed, eye, depth) for eye, cam in cameras.items()]


def held_start(inputs: list[FrameInput], extra: int, period_ns: int) -> list[FrameInput]:
    """The trace's frames after `extra` frames that hold its first one, all renumbered from 0: a longer warm-up
    comes before the trace starts (a temporal method's history: an eval group scores the same stretch of the trace
    whatever its warm-up, and `hmdrt render` shows a method's steady image of a view)."""
    held = [inputs[0]] * extra + inputs
    return [dataclasses.replace(inp, frame=k, t_ns=k * period_ns) for k, inp in enumerate(held)]


def render_frames(
    method: Method, profile: HmdProfile, inputs: list[FrameInput], eyes: tuple[str, ...], seed: int = 0
) -> Iterator[tuple[FrameInput, list[np.ndarray], FrameStats]]:
    """Render each input through `method` for the given eyes; yields the per-eye images and stats."""
    for inp in inputs:
        stats = FrameStats()
        cameras = eye_cameras(profile, inp.pose, eyes)
        images = [method.render(req, stats) for req in frame_requests(inp, cameras, seed)]
        yield inp, images, stats
