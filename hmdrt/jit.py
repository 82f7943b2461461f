"""The numba flags every kernel shares, defined once.

kernel: a parallel pass over an image or a batch (releases the GIL, cached on disk). serial: a kernel
too small to pay for the thread pool, or the body of one block of a parallel kernel. inline: a
per-element helper inlined into the kernels that call it.
"""

from __future__ import annotations

import numba as nb

kernel = nb.njit(parallel=True, cache=True, nogil=True)
serial = nb.njit(cache=True, nogil=True)
inline = nb.njit(cache=True, nogil=True, inline="always")
