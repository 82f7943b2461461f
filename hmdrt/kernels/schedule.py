"""Blocks of a parallel kernel handed to numba's threads as each one frees up.

numba's omp and workqueue threading layers split a prange statically, into one contiguous share per thread,
and `numba.parallel_chunksize` does not change that (numba 0.68: it cuts the range into more pieces, which the
layer still deals out in contiguous shares). When blocks differ in cost (rays on the mirror spheres or the sky,
the fovea or the periphery, the near field at the bottom of the image) one thread then finishes early and
waits. A kernel that takes its blocks from a shared counter instead runs a prange over its threads, each of
which claims the next block until none is left, and is called through dynamic(), which appends the counter
and the thread count to its arguments (read outside: nb.get_num_threads() in a kernel keeps it from caching):

    @kernel
    def _rows(..., counter, threads):
        for _ in nb.prange(threads):
            b = claim(counter)
            while b < blocks:
                ...  # block b
                b = claim(counter)
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from hmdrt.kernels.jit import serial

T = TypeVar("T")


@intrinsic
def _fetch_add(typingctx, counter, delta):
    """Atomically add delta to counter[0] (a C-contiguous int64 array) and return its value before."""
    if not (isinstance(counter, types.Array) and counter.dtype == types.int64 and delta == types.int64):
        return None

    def codegen(context, builder, sig, args):
        array = context.make_array(sig.args[0])(context, builder, args[0])
        ptr = cgutils.get_item_pointer(context, builder, sig.args[0], array, [ir.Constant(ir.IntType(64), 0)])
        return builder.atomic_rmw("add", ptr, args[1], "monotonic")

    return types.int64(counter, delta), codegen


@serial
def claim(counter: np.ndarray) -> int:
    """The next unclaimed block of the kernel call that `counter` (dynamic's) counts for."""
    return _fetch_add(counter, np.int64(1))


def dynamic(kernel: Callable[..., T], *args: Any) -> T:
    """kernel(*args, counter, threads): a parallel kernel that claims its blocks, on numba's current thread count,
    with a counter of its own (calls from several threads do not share one)."""
    return kernel(*args, np.zeros(1, np.int64), nb.get_num_threads())
