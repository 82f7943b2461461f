"""Stage times from inside a fused kernel: each thread adds the nanoseconds of every step it runs to its own
tally, and the kernel's wall time is credited to FrameStats in those proportions, so a fused pass still
shows where its time goes (raygen, primary, surface, lightgen, shadow, ...) under the usual stage names.

A step is a whole block's batch (a few hundred rays), so the clock is read a few times per block, not per ray.
"""

from __future__ import annotations

import numpy as np
from numba import types

from hmdrt.kernels.jit import inline
from hmdrt.telemetry.stats import FrameStats

STAGES = ("raygen", "primary", "secondary", "surface", "lightgen", "shadow", "area", "ao", "shade", "gbuffer")
N_STAGES = len(STAGES)
RAYGEN, PRIMARY, SECONDARY, SURFACE, LIGHTGEN, SHADOW, AREA, AO, SHADE, GBUFFER = range(N_STAGES)
RAY_KINDS = ("primary", "secondary", "shadow", "area", "ao")
RAYS_PRIMARY, RAYS_SECONDARY, RAYS_SHADOW, RAYS_AREA, RAYS_AO = range(2 * N_STAGES, 2 * N_STAGES + 5)
NEED = RAYS_AO + 1  # the largest wavefront level a thread met (its scratch grows to it)
TALLY = NEED + 1  # int64 words per thread: ns per stage, runs per stage, rays per kind, NEED

_CLOCK_MONOTONIC = 1
_clock_gettime = types.ExternalFunction("clock_gettime", types.int32(types.int32, types.intp))


@inline
def now(clock):
    """Monotonic nanoseconds; clock is an int64 (2,) scratch for the timespec."""
    _clock_gettime(_CLOCK_MONOTONIC, clock.ctypes.data)
    return clock[0] * 1_000_000_000 + clock[1]


@inline
def tick(tally, clock, stage, since):
    """Charge the time since `since` to `stage`; returns now, the start of the next step."""
    t = now(clock)
    tally[stage] += t - since
    tally[N_STAGES + stage] += 1
    return t


def credit(stats: FrameStats, wall_ms: float, tallies: list[np.ndarray]) -> None:
    """Credit wall_ms of a fused kernel to the stages its threads ran, in proportion to their thread time,
    and count its rays."""
    total = sum(tallies[1:], tallies[0])
    ns = total[:N_STAGES]
    spent = int(ns.sum())
    prefix = "/".join(stats._open)  # noqa: SLF001 - the enclosing stages, as FrameStats.stage names them
    for k, name in enumerate(STAGES):
        if total[N_STAGES + k]:
            key = f"{prefix}/{name}" if prefix else name
            share = wall_ms * int(ns[k]) / spent if spent else 0.0
            stats.stages_ms[key] = stats.stages_ms.get(key, 0.0) + share
    for k, kind in enumerate(RAY_KINDS):
        stats.count(kind, int(total[RAYS_PRIMARY + k]))
