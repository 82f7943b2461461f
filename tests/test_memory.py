"""Persistent buffers come with their pages written (hmdrt.kernels.memory.touched): a frame that first fills one pays
no page faults for it."""

from __future__ import annotations

import mmap
import resource

import numpy as np

from hmdrt.kernels.memory import touched


def _faults() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt


def test_a_touched_buffer_is_zero_and_writing_it_faults_no_page() -> None:
    shape = (4, 1 << 20)  # 16 MB of float32: thousands of pages, or eight huge pages
    region = mmap.mmap(-1, 16 << 20)  # never touched, unlike memory malloc may hand back
    fresh = np.frombuffer(region, np.float32).reshape(shape)
    before = _faults()
    fresh[...] = 1.0
    assert _faults() - before >= 8  # the check sees first touches
    del fresh
    region.close()

    buffer = touched(shape)
    assert buffer.shape == shape and buffer.dtype == np.float32 and not buffer.any()
    before = _faults()
    buffer[...] = 1.0
    assert _faults() - before < 4
