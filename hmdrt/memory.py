"""Keep freed memory mapped between frames.

glibc hands large freed blocks back to the kernel, so every frame's fresh arrays touch new pages; on
these machines a first touch costs about 1 ms per MB, more than many of a frame's passes (measured:
a 1280x1440 reprojection 57 ms with fresh pages, 13 ms without). Raising glibc's trim and mmap
thresholds keeps freed blocks in the heap for reuse. Process-wide, applied once, glibc only.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

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
