"""What the benches measure against, in the same run: bare embreex's rays per second, a numba copy's bytes
per second, and the frames a bench renders (a still view or the built-in head path)."""

from __future__ import annotations

import statistics
import time
from concurrent.futures import ThreadPoolExecutor

import numba as nb
import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from hmdrt.foveation import FrameRequest
from hmdrt.jit import kernel
from hmdrt.optics import EyeCamera, HmdProfile
from hmdrt.optics.camera import pixel_centres
from hmdrt.scene import Scene
from hmdrt.scene.pack import pack
from hmdrt.sequence import eye_cameras, frame_requests, sequence_inputs


@kernel
def _copy(src, dst):
    for i in nb.prange(src.shape[0]):
        for j in range(src.shape[1]):
            dst[i, j] = src[i, j]


def copy_rate(width: int, height: int, repeats: int = 15) -> float:
    """Bytes per second (read + write) of a parallel numba copy of a (height * width, 4) float32 image."""
    src = np.random.default_rng(0).random((width * height, 4), dtype=np.float32)
    dst = np.empty_like(src)
    _copy(src, dst)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        _copy(src, dst)
        times.append(time.perf_counter() - t)
    return 2 * src.nbytes / statistics.median(times)


def bare_embree_rate(scene: Scene, camera: EyeCamera, threads: int, repeats: int = 5) -> float:
    """Rays per second of bare embreex on the camera's primary rays, split in equal parts over `threads`."""
    geometry = pack(scene).geometry
    bare = rtcore_scene.EmbreeScene()
    TriangleMesh(bare, geometry.vertices, geometry.faces)
    dirs = camera.directions(pixel_centres(camera.width, camera.height))
    origins = np.empty_like(dirs)
    origins[:] = camera.position
    bare.run(origins[:1], dirs[:1])  # commit the BVH outside the timing
    parts = [slice(p[0], p[-1] + 1) for p in np.array_split(np.arange(len(dirs)), threads)]
    times = []
    with ThreadPoolExecutor(threads) as pool:
        for _ in range(repeats):
            t = time.perf_counter()
            list(pool.map(lambda s: bare.run(origins[s], dirs[s], output=1), parts))
            times.append(time.perf_counter() - t)
    return len(dirs) / statistics.median(times)


def left_eye_requests(
    scene: Scene, profile: HmdProfile, frames: int, trace: str | None, gaze: str = "0,0"
) -> list[FrameRequest]:
    """The left eye's frame requests: a fixed gaze with the head still (trace None), or the built-in head path."""
    inputs, _ = sequence_inputs(scene.start, profile.period_ns, frames, trace, gaze)
    return [frame_requests(inp, eye_cameras(profile, inp.pose, ("left",)), 0)[0] for inp in inputs]
