"""The numba flags every kernel shares, defined once.

kernel: a parallel pass over an image or a batch (releases the GIL, cached on disk). serial: a kernel
too small to pay for the thread pool, the body of one block of a parallel kernel, or a small helper of
scalars and arrays (LLVM inlines those on its own). inline: a per-element helper that takes or returns
grouped arguments (NamedTuples), inlined in numba's IR where LLVM would leave a call, and a thin step that
hands grouped arguments on to others (the Whitted kernel's steps, hmdrt.trace.wavefront): numba compiles each
serial function into a library in which LLVM optimises and compiles again everything it calls, so a layer
of steps costs a compile of all below it. Each inlining re-types its caller, so only those: with every helper
of the tracer inlined, its cold compile takes 70 s of CPU, not 21 s.

A prange's index is unsigned (uint64) in the loop numba runs, and signed (int64) where numba first types the
kernel, before it makes the loop parallel: a serial helper given the index as it is compiles for both, the int64
version for nothing. So a kernel hands a helper the index converted: np.uint64(index), the type the loop runs with,
or np.int64(index) where the helper's other callers pass an int64 (kim21's first start compiled 28 functions fewer;
tests/test_compile_aside.py checks every method).

SPIN_COUNT: how long the threads of numba's OpenMP layer (libgomp) poll for the next parallel kernel before they
sleep. libgomp's own default, 300,000 polls (several milliseconds on the Xeon), has them burn a core after every
kernel, which the tracer's threads, the display thread and the next kernel's Python need on a 2-core machine; 20,000
polls still span the Python between two kernels. Set, unless the environment already sets GOMP_SPINCOUNT, before
libgomp loads (at the first parallel kernel), which reads it then.
"""

from __future__ import annotations

import os

import numba as nb

SPIN_COUNT = 20_000
os.environ.setdefault("GOMP_SPINCOUNT", str(SPIN_COUNT))

kernel = nb.njit(parallel=True, cache=True, nogil=True)
serial = nb.njit(cache=True, nogil=True)
# serial, with each a * b + c in one instruction and one rounding (FMA), for per-ray math made of polynomials and dot
# products: a quarter off making the AO rays; the bits differ from unfused arithmetic, the same from run to run
fused = nb.njit(cache=True, nogil=True, fastmath={"contract"})
inline = nb.njit(cache=True, nogil=True, inline="always")
