"""What runs on a Dask worker for `hmdrt eval --cluster` (hmdrt.evaluate.cluster submits it): row blocks of a
ground truth, their assembly, and whole groups rendered by the serial runner's own code. Each task traces on
`threads` threads (the config's, else 1: a worker thread per core is Dask's parallelism), with a tracer of its
scene kept for the thread's next task."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager

import numba as nb
import numpy as np

from hmdrt.errors import HmdrtError
from hmdrt.evaluate.config import EvalConfig
from hmdrt.evaluate.gaze import TraceFrames
from hmdrt.evaluate.groups import GroupKey, GroupResult
from hmdrt.evaluate.runner import plan_group, run_group
from hmdrt.evaluate.truth import TruthCache, scene_digest, truth_rows
from hmdrt.optics import EyeCamera
from hmdrt.scene import load_scene
from hmdrt.trace.integrator import Whitted

_held = threading.local()  # this thread's (scene name, threads) and its tracer and digest


def threads_of(config: EvalConfig) -> int:
    """Tracing threads of each task: the config's, else one."""
    return config.threads or 1


@contextmanager
def _scene(name: str, threads: int) -> Iterator[tuple[Whitted, str]]:
    """The scene's tracer and digest, kept for the thread's next task on the same scene; numba's kernels on `threads`
    threads meanwhile (its count is per calling thread)."""
    held = getattr(_held, "value", None)
    if held is None or held[0] != (name, threads):
        if held is not None:
            held[1][0].close()
        scene = load_scene(name)
        _held.value = held = ((name, threads), (Whitted(scene, threads=threads), scene_digest(scene)))
    before = nb.get_num_threads()
    nb.set_num_threads(min(threads, nb.config.NUMBA_NUM_THREADS))
    try:
        yield held[1]
    finally:
        nb.set_num_threads(before)


def truth_block(scene: str, camera: EyeCamera, spp: int, seed: int, row0: int, rows: int, threads: int) -> np.ndarray:
    """Rows row0 to row0 + rows of a ground truth: the same pixels as the whole image's (truth_rows)."""
    with _scene(scene, threads) as (tracer, _):
        return truth_rows(tracer, camera, spp, seed, row0, rows)


def assemble(key: str, blocks: list[np.ndarray], shared: str | None) -> np.ndarray:
    """A truth from its row blocks in order, written into the shared cache folder where there is one."""
    image = np.concatenate(blocks)
    if shared is not None:
        TruthCache(shared).store(key, image)
    return image


def read_truth(key: str, camera: EyeCamera, shared: str) -> np.ndarray:
    """A truth the client found in the shared cache folder, read by the worker."""
    image = TruthCache(shared).load(key, camera)
    if image is None:
        raise HmdrtError(
            f"truth {key} is not in the cache folder {shared} here: a cache_dir the config names must be "
            "a folder every worker sees at that path"
        )
    return image


def held(image: np.ndarray) -> np.ndarray:
    """A truth the client had, sent with its task so that the scheduler can send it again if a worker is lost."""
    return image


def group(config: EvalConfig, key: GroupKey, frames: TraceFrames, truths: dict[str, np.ndarray]) -> GroupResult:
    """Render and score one group as the serial runner does, on its trace's `frames` (read by the client), its
    truths looked up by cache key; the rows name the worker."""
    from distributed import get_worker

    cache = TruthCache(config.cache_dir, config.truth_spp, config.seed)  # for its keys
    with _scene(key.scene, threads_of(config)) as (tracer, digest):

        def truth_of(camera: EyeCamera) -> np.ndarray:
            try:
                return truths[cache.key(digest, camera)]
            except KeyError:
                raise HmdrtError(
                    f"{key.scene}: a truth this worker needs was not sent: its scene or hmdrt differs from the client's"
                ) from None

        planned = plan_group(config, tracer, key, frames)
        return run_group(planned, config, truth_of, worker=get_worker().address)
