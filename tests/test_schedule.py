"""Blocks claimed from a shared counter (hmdrt.kernels.schedule): each exactly once, shared out by cost."""

import numba as nb
import numpy as np
import pytest

from hmdrt.kernels.schedule import claim, dynamic


@nb.njit(parallel=True, nogil=True)
def _record(costs, owner, counter, threads):
    """Block b spins costs[b] iterations and records which thread ran it, counting its runs."""
    for _ in nb.prange(threads):
        b = claim(counter)
        while b < len(costs):
            s = 0.0
            for i in range(costs[b]):
                s += np.sqrt(i + 1.0)
            owner[b, 0] = nb.get_thread_id() + 0.0 * s
            owner[b, 1] += 1
            b = claim(counter)


def test_every_block_runs_once():
    owner = np.zeros((100_000, 2), np.int64)
    dynamic(_record, np.zeros(100_000, np.int64), owner)
    assert (owner[:, 1] == 1).all()


@pytest.mark.skipif(nb.config.NUMBA_NUM_THREADS < 2, reason="needs two numba threads")
def test_costly_blocks_are_shared_out():
    # the costly blocks come first: numba's static split would give them all to one thread
    costs = np.array([2_000_000] * 8 + [10] * 8, np.int64)
    owner = np.zeros((16, 2), np.int64)
    dynamic(_record, costs, owner)  # compiled
    owner[:] = 0
    before = nb.get_num_threads()
    nb.set_num_threads(2)
    try:
        dynamic(_record, costs, owner)
    finally:
        nb.set_num_threads(before)
    assert (owner[:, 1] == 1).all()
    assert len(set(owner[:8, 0].tolist())) == 2, f"one thread ran every costly block: {owner[:8, 0]}"
