"""What frames are rendered with: the HMD profile, the scene and its tracer, the method and the eyes;
and the one step that turns a gaze and head-pose estimate into per-eye images.

The method can be swapped or retuned between frames (control `set`, the budget controller, a config
reload): the same method with new parameters keeps its history (Method.set_params); another method
starts fresh. Each eye's images are rendered into buffers of a pool (hmdrt.compositor.buffers), reused
once the display and the frame writer have let go of them.
"""

from __future__ import annotations

import logging
import time

import msgspec
import numpy as np

from hmdrt.compositor.buffers import BufferPool
from hmdrt.compositor.config import RunConfig
from hmdrt.compositor.samples import GazeEstimate, PoseEstimate
from hmdrt.errors import ConfigError
from hmdrt.foveation import MethodChoice
from hmdrt.foveation.base import EYES, Method
from hmdrt.optics import EyeCamera, HmdProfile, get_profile
from hmdrt.present.timewarp import timewarp
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import FrameInput, compose_pose, eye_cameras, frame_requests

log = logging.getLogger(__name__)

AHEAD = np.array([0.0, 0.0, -1.0])
READY_RENDERED, READY_WARPED = 3, 2  # image buffers per eye made before the first VSync (BufferPool ready)
WARM_UP_FRAMES = 2  # the first without history, the second with it: every stage a frame may run (Session.warm_up)
COMPILE_SIZE = (32, 36)  # pixels of the warm-up's frames against an empty scene: the kernels' types do not depend on it


def display_profile(config: RunConfig) -> HmdProfile:
    """The profile of the config's display, with its resolution and refresh overrides."""
    display = config.display
    profile = get_profile(display.profile)
    if display.resolution:
        profile = profile.with_resolution_text(display.resolution, "display.resolution")
    if display.refresh_hz:
        profile = msgspec.structs.replace(profile, refresh_hz=display.refresh_hz)
    return profile


class Session:
    def __init__(self, config: RunConfig):
        self.profile = display_profile(config)
        self.eyes = EYES if config.display.eyes == "both" else (config.display.eyes,)
        shape = (self.profile.height, self.profile.width, 3)
        # what a run holds at once, ready before the first VSync: the display's frame, the pending one and the one
        # being rendered; a warp in progress and the warp shown
        self.pools = {eye: BufferPool(shape, ready=READY_RENDERED) for eye in self.eyes}
        self.warp_pools = {eye: BufferPool(shape, ready=READY_WARPED) for eye in self.eyes}
        self.scene = load_scene(config.scene)
        self.tracer = Whitted(self.scene, threads=config.run.threads or None, aside=True)
        self.choice = config.method_choice
        try:
            self.method: Method = self.choice.make(self.tracer)
        except ConfigError:
            self.tracer.close()
            raise

    def warm_up(self) -> None:
        """Compile the kernels and allocate the tracer's buffers before the first VSync (a compile on the display
        thread would stall it for seconds). First the method's own kernels, in WARM_UP_FRAMES small frames of a
        throwaway instance against an empty scene (Whitted.empty_scene: on a first run they compile while a second
        process compiles the tracer, hmdrt.trace.compile_aside); then the timewarp, on a tiny frame (its kernel's
        types do not depend on the size: loaded from the cache where that process, done with the tracer, compiled
        it first); then WARM_UP_FRAMES frames of another throwaway instance at the display's size, whose first trace
        waits for that process, and a timewarp of one. The first frame has no history, the second runs the stages
        that need one. The method itself starts without history."""
        self._compile_ahead()
        tiny = EyeCamera.for_eye(self.profile.with_resolution(8, 8), self.head(None), self.eyes[0])
        timewarp(np.zeros((8, 8, 3), np.float32), tiny, tiny)
        method, self.method = self.method, self.choice.make(self.tracer)
        try:
            for frame in range(WARM_UP_FRAMES):
                images, cameras, _ = self.render(frame, None, None, 0, FrameStats())
            camera = next(iter(cameras.values()))
            timewarp(images[0], camera, camera)
        finally:
            self.method = method

    def _compile_ahead(self) -> None:
        """warm_up's small frames against an empty scene. They only save time: one that fails (a method of a size it
        cannot render) is logged and leaves its kernels to the frames at the display's size."""
        small = eye_cameras(self.profile.with_resolution(*COMPILE_SIZE), self.head(None), self.eyes)
        directions, depth = self.directions(None)
        with self.tracer.empty_scene():
            try:
                ahead = self.choice.make(self.tracer)
                for frame in range(WARM_UP_FRAMES):
                    for request in frame_requests(FrameInput(frame, 0, self.head(None), directions, depth), small, 0):
                        ahead.render(request, FrameStats())
            except Exception as exc:  # noqa: BLE001 - a failure here only loses the head start
                log.warning(
                    "compiling %s ahead at %dx%d failed (%s); its frames compile it",
                    self.choice.name,
                    *COMPILE_SIZE,
                    exc,
                )

    @property
    def spec(self) -> str:
        """The method chosen last (by the config, a reload or the control socket), as "name?key=value&..."."""
        return str(self.choice)

    def set_method(self, choice: MethodChoice) -> None:
        """Use `choice` from the next frame: the method retuned in place when only its parameters change, left as it
        is when it renders with these parameters already (a start, or a reload that keeps the method)."""
        if choice.name != self.method.name:
            self.method = choice.make(self.tracer)
        elif choice != self.current():
            self.method.set_params(choice.params)
        self.choice = choice

    def params(self) -> dict:
        return msgspec.to_builtins(self.method.params)

    def current(self) -> MethodChoice:
        """The method as it renders now, with the parameters the budget controller may have changed."""
        return MethodChoice(self.method.name, self.method.params)

    def render(
        self,
        frame_id: int,
        gaze,
        pose,
        seed: int,
        stats: FrameStats,
        delay_ns: int = 0,
        cameras: dict[str, EyeCamera] | None = None,
    ) -> tuple[list[np.ndarray], dict, int]:
        """The eyes' images for a gaze and head-pose estimate (None: straight ahead, the scene's
        start pose), the eye cameras they were rendered with (`cameras`: cameras_for(pose), when the caller has
        them already), and the nanoseconds the method's render took (with delay_ns of sleep added: a slower
        renderer, for tests and benchmarks)."""
        directions, depth = self.directions(gaze)
        frame = FrameInput(frame_id, 0, self.head(pose), directions, depth)
        cameras = self.cameras_for(pose) if cameras is None else cameras
        images, start = [], time.perf_counter_ns()
        for request in frame_requests(frame, cameras, seed):
            images.append(self.method.render(request, stats, self.pools[request.eye].take()))
        if delay_ns:
            with stats.stage("render_delay"):
                time.sleep(delay_ns / 1e9)
        took = time.perf_counter_ns() - start
        return images, cameras, took

    @staticmethod
    def directions(gaze: GazeEstimate | None) -> tuple[dict[str, np.ndarray], float | None]:
        """Each eye's gaze direction (head frame) and the vergence depth of a gaze estimate (None: straight ahead)."""
        if gaze is None:
            return {"left": AHEAD, "right": AHEAD}, None
        return {"left": gaze.left, "right": gaze.right}, gaze.depth_m

    def head(self, pose: PoseEstimate | None) -> Pose:
        """The head in the scene at a pose estimate, which is relative to where its trace started (None: the scene's
        start pose)."""
        return self.scene.start if pose is None else compose_pose(self.scene.start, pose)

    def cameras_for(self, pose: PoseEstimate | None) -> dict[str, EyeCamera]:
        """The eye cameras at a head-pose estimate (None: the scene's start pose): a frame is rendered with them, and
        a repeat is warped to them at the pose predicted for its VSync."""
        return eye_cameras(self.profile, self.head(pose), self.eyes)

    def close(self) -> None:
        self.tracer.close()
