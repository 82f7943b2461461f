"""The numba flags every kernel shares, defined once.

kernel: a parallel pass over an image or a batch (releases the GIL, cached on disk). serial: a kernel
too small to pay for the thread pool, the body of one block of a parallel kernel, or a small helper of
scalars and arrays (LLVM inlines those on its own). inline: a per-element helper that takes or returns
grouped arguments (NamedTuples), inlined in numba's IR where LLVM would leave a call; each such inlining
re-types its caller, so only those helpers, or a hot kernel's cold compile takes a minute.
"""

from __future__ import annotations

import numba as nb

kernel = nb.njit(parallel=True, cache=True, nogil=True)
serial = nb.njit(cache=True, nogil=True)
inline = nb.njit(cache=True, nogil=True, inline="always")
