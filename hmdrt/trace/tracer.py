"""The one owner of Embree (through embreex): builds the scene once and traces batches of rays in
tiles on a thread pool; embreex releases the GIL, so tiles run in parallel. The calling thread traces
tiles too, and a batch smaller than two tiles never leaves it: handing work to a pool thread costs about
0.1-0.3 ms here, as much as tracing a few thousand rays (bench/trace_throughput.py --rays)."""

from __future__ import annotations

import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import numpy as np
from embreex import rtcore_scene
from embreex.mesh_construction import TriangleMesh

from hmdrt.scene.pack import Geometry

EMBREE_MISS_T = 1e37  # tfar that embreex reports for rays that hit nothing
MIN_TILE = 8192  # rays: smaller batches are traced on the calling thread alone


class Hits(NamedTuple):
    """First hits of n rays: prim is -1 on a miss; t is the hit distance; (u, v) Embree barycentrics."""

    prim: np.ndarray  # (n,) int32
    t: np.ndarray  # (n,) float32
    u: np.ndarray  # (n,) float32
    v: np.ndarray  # (n,) float32


def _check_rays(origins: np.ndarray, directions: np.ndarray) -> None:
    if origins.dtype != np.float32 or directions.dtype != np.float32:
        raise TypeError("origins and directions must be float32")
    if origins.ndim != 2 or origins.shape[1] != 3 or directions.shape != origins.shape:
        raise ValueError(f"origins and directions must both be (n, 3), got {origins.shape} and {directions.shape}")


class Tracer:
    """Embree scene over one Geometry; intersect() and occluded() take float32 (n, 3) rays."""

    def __init__(
        self, geometry: Geometry, threads: int | None = None, tile_rays: int = 1 << 15, min_tile_rays: int = MIN_TILE
    ):
        self.threads = threads or os.cpu_count() or 1
        self.tile_rays = tile_rays
        self.min_tile_rays = min_tile_rays
        self.triangles = len(geometry.faces)
        self._scene = rtcore_scene.EmbreeScene()
        if self.triangles:
            TriangleMesh(self._scene, geometry.vertices, geometry.faces)
            # commit now: embreex commits lazily on the first run(), which must not race across threads
            self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32))
        self._pool = ThreadPoolExecutor(max(self.threads - 1, 1), thread_name_prefix="hmdrt-trace")

    def tiles(self, n: int) -> list[slice]:
        """How n rays are split into tiles: one per thread where that gives tiles of min_tile_rays to tile_rays rays."""
        step = max(self.min_tile_rays, min(self.tile_rays, -(-n // self.threads)))
        return [slice(i, min(i + step, n)) for i in range(0, n, step)]

    def _each_tile(self, tile: Callable[[slice], None], n: int) -> None:
        """tile(s) for every tile of n rays, taken in turn by this thread and up to threads - 1 pool threads."""
        tiles = self.tiles(n)
        queue = iter(tiles)  # shared: each thread takes the next tile when it is free (next() holds the GIL)

        def drain() -> None:
            for s in queue:
                tile(s)

        helpers = [self._pool.submit(drain) for _ in range(min(self.threads, len(tiles)) - 1)]
        drain()
        for helper in helpers:
            helper.result()

    def intersect(self, origins: np.ndarray, directions: np.ndarray, tfar: float | np.ndarray = EMBREE_MISS_T) -> Hits:
        """First hit along each ray within (0, tfar]."""
        _check_rays(origins, directions)
        n = len(origins)
        if n == 0 or self.triangles == 0:
            return Hits(
                np.full(n, -1, np.int32),
                np.full(n, np.inf, np.float32),
                np.zeros(n, np.float32),
                np.zeros(n, np.float32),
            )
        hits = Hits(np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32))
        scalar_far = np.ndim(tfar) == 0
        far = None if scalar_far else np.asarray(tfar, dtype=np.float32)

        def tile(s: slice) -> None:
            # embreex writes the hit distance into the tfar array it is given, so each tile gets its own
            dists = float(tfar) if scalar_far else far[s].copy()
            r = self._scene.run(origins[s], directions[s], dists=dists, output=1)
            hits.prim[s] = r["primID"]
            np.copyto(hits.t[s], r["tfar"])
            hits.t[s][r["primID"] < 0] = np.inf
            hits.u[s] = r["u"]
            hits.v[s] = r["v"]

        self._each_tile(tile, n)
        return hits

    def occluded(self, origins: np.ndarray, directions: np.ndarray, tfar: np.ndarray) -> np.ndarray:
        """Whether anything lies along each ray within (0, tfar]; bool (n,)."""
        _check_rays(origins, directions)
        n = len(origins)
        out = np.zeros(n, dtype=bool)
        if n == 0 or self.triangles == 0:
            return out
        scalar_far = np.ndim(tfar) == 0
        far = None if scalar_far else np.asarray(tfar, dtype=np.float32)

        def tile(s: slice) -> None:
            dists = float(tfar) if scalar_far else far[s].copy()
            out[s] = self._scene.run(origins[s], directions[s], dists=dists, query="OCCLUDED") != -1

        self._each_tile(tile, n)
        return out

    def close(self) -> None:
        self._pool.shutdown(wait=True)

    def __enter__(self) -> Tracer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
