"""No frame pays for touching memory for the first time.

On these machines the first write to a page costs far more than a frame's passes: 1-12 ms per MB
(measured: a 1280x1440 reprojection 57 ms with fresh pages, 13 ms without; 16 MB written in 191 ms fresh,
1.5 ms touched). So glibc keeps freed blocks for reuse (retain_freed_memory: it would hand large ones back
to the kernel, and every frame's fresh arrays would touch new pages), and buffers that later frames fill
one by one, a ring's slots or a pool's images, are written whole when they are allocated (touched).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

import numpy as np

M_TRIM_THRESHOLD, M_TOP_PAD, M_MMAP_THRESHOLD = -1, -2, -3  # glibc's mallopt parameters


@functools.cache
def retain_freed_memory() -> bool:
    """Ask glibc to keep freed memory for reuse; False where the C library is not glibc."""
    name = ctypes.util.find_library("c")
    try:
        libc = ctypes.CDLL(name or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    return all(
        mallopt(param, value) == 1
        for param, value in ((M_MMAP_THRESHOLD, 1 << 30), (M_TRIM_THRESHOLD, (1 << 31) - 1), (M_TOP_PAD, 1 << 28))
    )


def touched(shape: int | tuple[int, ...], dtype: type | np.dtype = np.float32) -> np.ndarray:
    """Zeros whose every page is written now. A persistent buffer that a later frame writes first (a ring's
    slot, a pool's new image) would make that frame pay the first touch of its pages, which here costs far more
    than the pass (kim21's reuse pass wrote its 1280x1440 history slot in 250-550 ms in each of the frames that
    first wrote a slot, in 24 ms once every slot had been written)."""
    out = np.empty(shape, dtype)
    out.fill(0)
    return out
