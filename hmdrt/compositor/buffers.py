"""Image buffers that the compositor reuses once nothing holds them, so that steady-state frames allocate no images.

A rendered or warped image is handed on without a copy: to the display (the frame it latched and shows, the
frames pending for it), the frame writer's queue and the snapshot command. The pool does not track them:
a buffer is free again when the pool's own reference is the only one left (Python's reference count, which
numpy views add to through their base), and only the thread that takes buffers from a pool hands them out,
so a free buffer cannot be reached by another thread.
"""

from __future__ import annotations

import sys
from collections.abc import Iterable

import numpy as np

from hmdrt.kernels.memory import touched

MOST_POOLED = 16  # per pool: more than the display, its pending frames and the writer's queue hold at once


def _refs(buffers: list[np.ndarray], i: int) -> int:
    return sys.getrefcount(buffers[i])


class BufferPool:
    """float32 images of one shape; take() returns one that no one else holds, allocating only when all are held."""

    def __init__(self, shape: tuple[int, ...], most: int = MOST_POOLED, ready: int = 0):
        """ready: buffers allocated, and their pages written, now (memory.touched): a buffer first taken in a
        frame would otherwise make that frame pay the first touch of its pages (about 60 ms for a 640x720
        image here, two periods at 30 Hz)."""
        self.shape = shape
        self.most = most
        self._buffers: list[np.ndarray] = [touched(shape) for _ in range(min(ready, most))]
        self._idle = _refs([np.empty(0, np.float32)], 0)  # the count of a buffer only the pool refers to
        self.allocated = len(self._buffers)  # buffers allocated so far: steady once every holder's share is in the pool

    def take(self) -> np.ndarray:
        """A buffer nothing else refers to; its contents are what it last held. Beyond `most` buffers in use,
        a new one is allocated each time and not pooled, so that a caller keeping every image does not grow
        the pool without bound."""
        for i in range(len(self._buffers)):
            if _refs(self._buffers, i) <= self._idle:
                return self._buffers[i]
        buffer = np.empty(self.shape, np.float32)
        self.allocated += 1
        if len(self._buffers) < self.most:
            self._buffers.append(buffer)
        return buffer

    @property
    def pooled(self) -> int:
        return len(self._buffers)


def counts(pools: Iterable[BufferPool]) -> dict[str, int]:
    """Buffers the pools hold and have allocated in all."""
    pools = list(pools)
    return {"pooled": sum(p.pooled for p in pools), "allocated": sum(p.allocated for p in pools)}
