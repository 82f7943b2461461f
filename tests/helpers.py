"""Test helpers: small renders of real scenes through the real tracer."""

from __future__ import annotations

from pathlib import Path

import msgspec
import numpy as np

from hmdrt.foveation import FrameRequest, make_method
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.scene import Scene, load_scene
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.gbuffer import GBuffer
from hmdrt.trace.integrator import Whitted

DATA = Path(__file__).parent / "data"
FORWARD = np.array([0.0, 0.0, -1.0])


def render(
    scene: Scene | str,
    width: int = 64,
    height: int = 72,
    method: str = "full",
    pose: Pose | None = None,
    seed: int = 0,
    ipd_mm: float | None = None,
    **options,
) -> tuple[np.ndarray, FrameStats]:
    """One frame of a scene through sim-cpu optics at a small resolution."""
    scene = load_scene(scene) if isinstance(scene, str) else scene
    profile = get_profile("sim-cpu").with_resolution(width, height)
    if ipd_mm is not None:
        profile = msgspec.structs.replace(profile, ipd_mm=ipd_mm)
    with Whitted(scene) as tracer:
        stats = FrameStats()
        cam = EyeCamera.for_eye(profile, pose or scene.start)
        image = make_method(method, tracer, **options).render(FrameRequest(cam, FORWARD, 0, seed), stats)
    return image, stats


def trace_gbuffer(scene: Scene, camera: EyeCamera, xy: np.ndarray) -> tuple[np.ndarray, GBuffer, FrameStats]:
    """Radiance and G-buffer of camera samples xy (n, 2)."""
    with Whitted(scene) as tracer:
        stats = FrameStats()
        gbuf = GBuffer.empty(len(xy))
        rgb = tracer.trace_samples(camera, xy, np.arange(len(xy)), stats, gbuf)
    return rgb, gbuf, stats
