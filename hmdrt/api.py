"""hmdrt as a library: render one eye's frame with its G-buffer, run the compositor for N frames in virtual time,
and read and write gaze traces (docs/api.md has an example of each).

The functions here build what `hmdrt render` and `hmdrt run` build (the scene's tracer, the method, the
compositor) and return arrays and reports rather than files.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import msgspec
import numpy as np
import zmq

from hmdrt.compositor.config import RunConfig, load_config
from hmdrt.compositor.daemon import Compositor
from hmdrt.foveation import FrameRequest, MethodChoice
from hmdrt.optics import EyeCamera, HmdProfile, get_profile, pixel_centres
from hmdrt.replay import load_trace
from hmdrt.replay.trace import Sample, TraceReading, write_trace
from hmdrt.scene import Scene, load_scene
from hmdrt.spatial import Pose, gaze_direction
from hmdrt.telemetry.stats import FrameStats
from hmdrt.telemetry.view import Report
from hmdrt.trace.gbuffer import GBuffer
from hmdrt.trace.integrator import Whitted

__all__ = [
    "GBufferImage",
    "RenderedFrame",
    "Report",
    "Sample",
    "TraceReading",
    "load_trace",
    "render_frame",
    "run_compositor",
    "trace_gbuffer",
    "write_trace",
]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class GBufferImage:
    """The primary hit of the view ray through every pixel centre of one eye, as (height, width) images.

    Every view ray starts at `origin`, so a hit lies at origin + depth * direction (`position`). Ids: object_id
    indexes the scene's meshes, triangle_id the scene's triangles with its meshes' concatenated in order
    (hmdrt.scene.pack); both are -1 where the ray hit nothing.
    """

    depth: np.ndarray  # (h, w) float32 hit distance along the unit ray, metres; inf on a miss
    position: np.ndarray  # (h, w, 3) float32 world position of the hit; nan on a miss
    normal: np.ndarray  # (h, w, 3) float32 shading normal, facing the ray; zero on a miss
    normal_geometric: np.ndarray  # (h, w, 3) float32 the triangle's normal, facing the ray; zero on a miss
    object_id: np.ndarray  # (h, w) int32
    triangle_id: np.ndarray  # (h, w) int32
    origin: np.ndarray  # (3,) float64 the eye's world position
    direction: np.ndarray  # (h, w, 3) float32 unit world direction of each pixel centre's view ray


@dataclass(frozen=True)
class RenderedFrame:
    """One eye's frame: the method's image, the G-buffer of its pixel centres, and what it took."""

    image: np.ndarray  # (h, w, 3) float32 linear RGB
    gbuffer: GBufferImage | None  # None when render_frame was asked for none
    camera: EyeCamera
    gaze: np.ndarray  # (3,) unit gaze direction in the head frame
    method: str  # the method with its options, as MethodChoice writes it
    stats: FrameStats  # the method's stage times and ray counts (not the G-buffer pass's)


def _trace(tracer: Whitted, camera: EyeCamera, xy: np.ndarray) -> tuple[np.ndarray, GBuffer, FrameStats]:
    stats = FrameStats()
    gbuf = GBuffer.empty(len(xy))
    rgb = tracer.trace_samples(camera, xy, np.arange(len(xy)), stats, gbuf)
    return rgb, gbuf, stats


def trace_gbuffer(
    scene: Scene, camera: EyeCamera, xy: np.ndarray, threads: int | None = None
) -> tuple[np.ndarray, GBuffer, FrameStats]:
    """Radiance (n, 3), G-buffer (primary and first secondary hit) and stats of the camera samples at pixel
    coordinates xy (n, 2), sample i seeded by i: the tracer's own output, for samples of the caller's choosing."""
    with Whitted(scene, threads) as tracer:
        return _trace(tracer, camera, xy)


def _gbuffer_image(tracer: Whitted, camera: EyeCamera) -> GBufferImage:
    """The G-buffer of every pixel centre, with the triangles the primary rays hit."""
    h, w = camera.height, camera.width
    xy = pixel_centres(w, h)
    _, gbuf, _ = _trace(tracer, camera, xy)
    directions = camera.directions(xy)
    origins = np.broadcast_to(camera.position.astype(np.float32), directions.shape)
    triangles = tracer.tracer.intersect(np.ascontiguousarray(origins), directions).prim
    hit = gbuf.primary
    position = camera.position + hit.depth[:, None].astype(np.float64) * directions
    position[~np.isfinite(hit.depth)] = np.nan
    return GBufferImage(
        depth=hit.depth.reshape(h, w),
        position=position.astype(np.float32).reshape(h, w, 3),
        normal=hit.normal_shading.reshape(h, w, 3),
        normal_geometric=hit.normal_geometric.reshape(h, w, 3),
        object_id=hit.object_id.reshape(h, w),
        triangle_id=triangles.reshape(h, w),
        origin=np.array(camera.position, dtype=np.float64),
        direction=directions.reshape(h, w, 3),
    )


def _gaze(gaze: Sequence[float] | np.ndarray) -> np.ndarray:
    """A unit head-frame gaze from (yaw, pitch) in degrees or a direction."""
    g = np.asarray(gaze, dtype=np.float64)
    if g.shape == (2,):
        g = np.array(gaze_direction(float(g[0]), float(g[1])))
    if g.shape != (3,) or not np.all(np.isfinite(g)) or not np.any(g):
        raise ValueError(f"gaze must be (yaw, pitch) in degrees or a finite, non-zero 3-vector, got {gaze!r}")
    return g / np.linalg.norm(g)


def render_frame(
    scene: str | Scene,
    profile: str | HmdProfile = "sim-cpu",
    method: str | MethodChoice = "full",
    gaze: Sequence[float] | np.ndarray = (0.0, 0.0),
    *,
    eye: Literal["left", "right"] = "left",
    resolution: tuple[int, int] | None = None,
    pose: Pose | None = None,
    seed: int = 0,
    threads: int | None = None,
    gbuffer: bool = True,
) -> RenderedFrame:
    """Render one eye's frame of `scene` through `profile`'s optics with `method` at `gaze`, as `hmdrt render` does.

    scene: a built-in name ("whitted", "voxel_city?size=10"), a scene .toml, a mesh file, or a Scene. profile: a
    profile name or .toml, or an HmdProfile; resolution (width, height) keeps its optics. method: a spec with
    options ("rrm?fovea_deg=5") or a MethodChoice. gaze: (yaw, pitch) in degrees, right and up positive, or a
    direction in the head frame. pose: the head in the world (default: the scene's start). gbuffer=False skips
    the G-buffer pass (a second trace of every pixel centre).
    """
    scene = load_scene(scene) if isinstance(scene, str) else scene
    profile = get_profile(profile) if isinstance(profile, str) else profile
    if resolution is not None:
        profile = profile.with_resolution(*resolution)
    choice = MethodChoice.parse(method) if isinstance(method, str) else method
    direction = _gaze(gaze)
    camera = EyeCamera.for_eye(profile, pose or scene.start, eye)
    with Whitted(scene, threads) as tracer:
        stats = FrameStats()
        image = choice.make(tracer).render(FrameRequest(camera, direction, 0, seed, eye), stats)
        gbuf = _gbuffer_image(tracer, camera) if gbuffer else None
    log.debug("rendered %s of %s at %dx%d, %s eye", choice, scene.name, profile.width, profile.height, eye)
    return RenderedFrame(image, gbuf, camera, direction, str(choice), stats)


def run_compositor(
    config: str | Path | RunConfig, frames: int = 30, *, virtual_time: bool = True, seed: int | None = None
) -> Report:
    """Run the compositor of a config file (or a RunConfig) for `frames` VSyncs and return its run report.

    In virtual time (the default) the clock moves one period per frame: the run never misses, takes as long as
    the rendering does, and reproduces bit for bit for the same config, trace and seed. virtual_time=False runs
    against the host clock, as `hmdrt run` does. The config's drivers feed it; its bus sockets (by default private
    ipc:// ones) are bound for the run and closed after. The report is a Report: the keys of `hmdrt run --report`'s
    JSON, read by key or attribute (report.latency_ms.gaze_to_photon.p99); Report.to_dict() gives the plain dict.
    """
    if frames < 1:
        raise ValueError(f"frames must be at least 1, got {frames}")
    if isinstance(config, RunConfig):
        run = msgspec.structs.replace(config.run, frames=frames, virtual_time=virtual_time)
        config = msgspec.structs.replace(config, run=run if seed is None else msgspec.structs.replace(run, seed=seed))
    else:
        config = load_config(config, frames=frames, virtual_time=virtual_time, seed=seed)
    context = zmq.Context()
    try:
        comp = Compositor(config, context=context)
        try:
            report = comp.run()
        finally:
            comp.close()
    finally:
        context.destroy(linger=0)
    log.info("ran %s: %d VSyncs, %d frames", config.source or "a config", report["vsyncs"], report["frames"])
    return Report(report)
