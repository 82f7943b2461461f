"""Stratified sample patterns: pixel jitter, area-light points and cosine-weighted hemisphere directions.

Each sample is a pure function of (key, index, dimension) through hmdrt.kernels.rng, so a seeded render
reproduces bit for bit however it is batched.
"""

import math

import numba as nb
import numpy as np

from hmdrt.kernels.jit import inline, kernel
from hmdrt.kernels.rng import uniform

# RNG dimensions: distinct streams for the different decisions made for one key
DIM_PIXEL, DIM_AREA, DIM_AO = 1, 16, 4096


@inline
def grid_dims(n):
    """(nx, ny) with nx * ny == n and nx <= ny as close to square as n allows (36 -> 6 x 6, 8 -> 2 x 4)."""
    nx = max(1, int(math.sqrt(n)))
    while n % nx:
        nx -= 1
    return nx, n // nx


def grid_shape(n: int) -> tuple[int, int]:
    """grid_dims for Python callers."""
    return tuple(int(v) for v in grid_dims(n))


@inline
def stratified(key, k, dim, nx, ny):
    """The k-th of nx * ny jittered strata of the unit square, for a given key and dimension."""
    ix = k % nx
    iy = k // nx
    return (ix + uniform(key, dim, 2 * k)) / nx, (iy + uniform(key, dim, 2 * k + 1)) / ny


@inline
def cosine_hemisphere(nx, ny, nz, s, t):
    """Cosine-weighted direction about unit normal n from a point (s, t) of the unit square."""
    r = math.sqrt(s)
    phi = 2.0 * math.pi * t
    lx, ly, lz = r * math.cos(phi), r * math.sin(phi), math.sqrt(max(0.0, 1.0 - s))
    # orthonormal basis (Duff et al. 2017)
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    tx, ty, tz = 1.0 + sign * nx * nx * a, sign * b, -sign * nx
    bx, by, bz = b, sign + ny * ny * a, -ny
    return lx * tx + ly * bx + lz * nx, lx * ty + ly * by + lz * ny, lx * tz + ly * bz + lz * nz


@kernel
def _jittered_pixels(width, row0, rows, nx, ny, seed, out):
    spp = nx * ny
    for r in nb.prange(rows):
        y = row0 + r
        for x in range(width):
            pixel = y * width + x
            key = pixel * 65599 + seed
            base = (r * width + x) * spp
            for k in range(spp):
                s, t = stratified(key, k, DIM_PIXEL, nx, ny)
                out[base + k, 0] = x + s
                out[base + k, 1] = y + t


def jittered_pixels(width: int, row0: int, rows: int, spp: int, seed: int = 0) -> np.ndarray:
    """Stratified jittered sample positions (rows * width * spp, 2) float32, spp consecutive per pixel."""
    nx, ny = grid_shape(spp)
    out = np.empty((rows * width * spp, 2), dtype=np.float32)
    _jittered_pixels(width, row0, rows, nx, ny, seed, out)
    return out
