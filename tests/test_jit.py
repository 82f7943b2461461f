"""numba's OpenMP threads poll only briefly for the next kernel (hmdrt.kernels.jit.SPIN_COUNT), measured in fresh
processes, since libgomp reads its setting once, when it loads."""

import json
import os
import subprocess
import sys

import numba as nb
import pytest

from hmdrt.kernels.jit import SPIN_COUNT

# A child that imports hmdrt's kernel flags, then runs a tiny parallel kernel 100 times with a 5 ms pause after each,
# and prints whether libgomp had loaded before the import, its GOMP_SPINCOUNT and the CPU it used over the wall time.
CHILD = """
import json, os, time
loaded_before = "libgomp" in open("/proc/self/maps").read()
import hmdrt.kernels.jit
import numba as nb
import numpy as np

@nb.njit(parallel=True)
def bump(a):
    for i in nb.prange(a.shape[0]):
        a[i] += 1.0

a = np.zeros(64)
bump(a)
cpu, wall = time.process_time(), time.perf_counter()
for _ in range(100):
    bump(a)
    time.sleep(0.005)
cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
print(json.dumps({"loaded_before": loaded_before, "layer": nb.threading_layer(),
                  "spin": os.environ.get("GOMP_SPINCOUNT"), "busy": cpu / wall}))
"""


def _child(spin: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "GOMP_SPINCOUNT"}
    env["NUMBA_NUM_THREADS"] = "2"
    if spin is not None:
        env["GOMP_SPINCOUNT"] = spin
    done = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_the_environment_keeps_its_own_setting():
    assert _child("1234")["spin"] == "1234"


@pytest.mark.skipif((os.cpu_count() or 1) < 2 or nb.config.NUMBA_NUM_THREADS < 2, reason="needs two cores")
def test_idle_threads_sleep_soon_after_a_kernel():
    ours = _child(None)
    if ours["layer"] != "omp":
        pytest.skip(f"numba runs on its {ours['layer']} threading layer here, not libgomp")
    assert not ours["loaded_before"]  # else the setting would come too late to count
    assert ours["spin"] == str(SPIN_COUNT)
    # libgomp's own default polls through most of each 5 ms pause on a core of its own; ours stops within a fraction
    gomp_default = _child("300000")
    assert ours["busy"] < 0.5 * gomp_default["busy"], (ours, gomp_default)
