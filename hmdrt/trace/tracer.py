"""The one owner of a scene's Embree BVH, and batch queries on it: intersect() and occluded() over float32
(n, 3) ray arrays, in parallel numba kernels that call Embree per ray (hmdrt.trace.embree). The Whitted
integrator calls Embree from its own fused kernel through `scene`; these batch calls serve tests, benches
and any caller with rays of its own."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, wait
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.kernels.jit import kernel
from hmdrt.kernels.schedule import claim, dynamic
from hmdrt.scene.pack import Geometry
from hmdrt.trace import embree
from hmdrt.trace.blocks import BLOCK


class Hits(NamedTuple):
    """First hits of n rays: prim is -1 on a miss; t is the hit distance (inf on a miss); (u, v) Embree barycentrics."""

    prim: np.ndarray  # (n,) int32
    t: np.ndarray  # (n,) float32
    u: np.ndarray  # (n,) float32
    v: np.ndarray  # (n,) float32


def _check_rays(origins: np.ndarray, directions: np.ndarray) -> None:
    if origins.dtype != np.float32 or directions.dtype != np.float32:
        raise TypeError("origins and directions must be float32")
    if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise ValueError(f"origins and directions must both be (n, 3), got {origins.shape} and {directions.shape}")


@kernel
def _intersect_kernel(scene, args, packets, origins, directions, tfar, hits, counter, threads):
    n = origins.shape[0]
    blocks = (n + BLOCK - 1) // BLOCK
    for _ in nb.prange(threads):
        packet = packets[nb.get_thread_id()]
        b = claim(counter)
        while b < blocks:
            start, stop = b * BLOCK, min(n, (b + 1) * BLOCK)
            embree.intersect_rays(scene, args, packet, origins, directions, tfar, hits, start, stop)
            b = claim(counter)


@kernel
def _occluded_kernel(scene, args, packets, origins, directions, tfar, out, counter, threads):
    n = origins.shape[0]
    blocks = (n + BLOCK - 1) // BLOCK
    for _ in nb.prange(threads):
        packet = packets[nb.get_thread_id()]
        b = claim(counter)
        while b < blocks:
            start, stop = b * BLOCK, min(n, (b + 1) * BLOCK)
            o, d, far, occ = origins[start:stop], directions[start:stop], tfar[start:stop], out[start:stop]
            embree.occluded_rays(scene, args, packet, o, d, far, occ, stop - start, 1)
            b = claim(counter)


class Tracer:
    """Embree scene over one Geometry; intersect() and occluded() trace on `threads` numba threads, and share() runs
    work on as many threads: the caller's and a pool of the tracer's own."""

    def __init__(self, geometry: Geometry, threads: int | None = None):
        self.threads = max(1, min(threads or os.cpu_count() or 1, nb.config.NUMBA_NUM_THREADS))
        self.triangles = len(geometry.faces)
        self.scene = embree.EmbreeScene(geometry.vertices, geometry.faces)
        self.packets = embree.packets(nb.config.NUMBA_NUM_THREADS)
        self.args = embree.coherent_args()
        self._pool = ThreadPoolExecutor(self.threads - 1, "hmdrt-tracer") if self.threads > 1 else None

    def share(self, work: Callable[[int], None]) -> None:
        """work(0) on the calling thread and work(1) ... work(threads - 1) on the pool, at once (each calls a kernel
        that releases the GIL); returns once all have, raising the first error."""
        futures = [self._pool.submit(work, t) for t in range(1, self.threads)] if self._pool else []
        try:
            work(0)
        finally:
            wait(futures)
        for future in futures:
            future.result()

    def run(self, fn, *args) -> None:
        """fn(*args), a parallel kernel that claims its blocks (hmdrt.kernels.schedule.dynamic: they differ in cost), on
        this tracer's threads (numba's count is per calling thread)."""
        before = nb.get_num_threads()
        nb.set_num_threads(self.threads)
        try:
            dynamic(fn, *args)
        finally:
            nb.set_num_threads(before)

    def _far(self, tfar: float | np.ndarray, n: int) -> np.ndarray:
        if np.ndim(tfar) == 0:
            return np.full(n, tfar, np.float32)
        far = np.ascontiguousarray(tfar, dtype=np.float32)
        if far.shape != (n,):
            raise ValueError(f"tfar must be a scalar or ({n},), got {far.shape}")
        return far

    def intersect(self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = embree.MISS_T) -> Hits:
        """First hit along each ray within (0, tfar]."""
        _check_rays(origins, directions)
        n = len(origins)
        hits = Hits(np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32))
        args = (np.ascontiguousarray(origins), np.ascontiguousarray(directions), self._far(tfar, n), hits)
        self.run(_intersect_kernel, self.scene.handle, self.args, self.packets, *args)
        return hits

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray) -> np.ndarray:
        """Whether anything lies along each ray within (0, tfar]; bool (n,). A ray with tfar <= 0 is not traced
        (False)."""
        _check_rays(origins, directions)
        n = len(origins)
        out = np.empty(n, dtype=bool)
        args = (np.ascontiguousarray(origins), np.ascontiguousarray(directions), self._far(tfar, n), out)
        self.run(_occluded_kernel, self.scene.handle, self.args, self.packets, *args)
        return out

    def close(self) -> None:
        if self._pool:
            self._pool.shutdown()
        self.scene.close()

    def __enter__(self) -> Tracer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
