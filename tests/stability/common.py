"""Helpers shared by the numerical stability tests in this folder."""

from __future__ import annotations

import math

import msgspec
import numpy as np

from hmdrt.bus.messages import Gaze
from hmdrt.foveation import FrameRequest, make_method
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.scene import Scene
from hmdrt.scene.model import Material
from hmdrt.spatial import Pose as HeadPose
from hmdrt.spatial import gaze_direction
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

MS = 1_000_000


FORWARD = np.array([0.0, 0.0, -1.0])


SKY = (0.3, 0.5, 0.8)


def camera(width: int = 64, height: int = 64, pose: HeadPose | None = None, centred: bool = False) -> EyeCamera:
    """A sim-cpu eye (90 x 94 degrees, symmetric) at a small resolution; centred: at the head (IPD 0)."""
    profile = get_profile("sim-cpu").with_resolution(width, height)
    if centred:
        profile = msgspec.structs.replace(profile, ipd_mm=0.0)
    return EyeCamera.for_eye(profile, pose or HeadPose())


def empty_scene() -> Scene:
    return Scene("empty", [], {"m": Material()}, background=SKY)


def render_frames(scene: Scene, method: str, gazes, width: int = 16, height: int = 16, **options):
    """Consecutive frames of the left eye through a method, one per gaze: (images, stats)."""
    profile = get_profile("sim-cpu").with_resolution(width, height)
    images, stats = [], []
    with Whitted(scene) as tracer:
        m = make_method(method, tracer, **options)
        cam = EyeCamera.for_eye(profile, scene.start)
        for frame, g in enumerate(gazes):
            s = FrameStats()
            images.append(m.render(FrameRequest(cam, np.asarray(g, dtype=np.float64), frame, 0), s))
            stats.append(s)
    return images, stats


def falloff(e: np.ndarray, r0: float, r1: float, p_min: float) -> np.ndarray:
    """weier2016's p(e) written out: 1 below r0, linear to p_min at r1, p_min beyond."""
    e = np.asarray(e, dtype=np.float64)
    ramp = 1.0 - (1.0 - p_min) * (e - r0) / (r1 - r0) if r1 > r0 else np.full_like(e, p_min)
    return np.where(e < r0, 1.0, np.where(e >= r1, p_min, ramp))


def gaze(seq: int, t_ns: int, yaw: float = 0.0, valid: bool = True) -> Gaze:
    return Gaze(seq=seq, t_host=t_ns, valid=valid, C=tuple(gaze_direction(yaw, 0.0)) if valid else None)


def yaw_of(v) -> float:
    return math.degrees(math.atan2(v[0], -v[2]))
