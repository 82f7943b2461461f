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
    """The k-th of nx * ny jittered strata of the unit square, for a given key and dimension. Without integer
    division or numba's zero-division checks, so that a loop over k vectorises: k // nx is the floor of
    (k + 0.5) / nx, which stays at least 0.5 / nx from an integer, far beyond the product's rounding for any
    k below 2**40."""
    iy = int((k + 0.5) * np.divide(1.0, nx))
    ix = k - iy * nx
    s = np.divide(ix + uniform(key, dim, 2 * k), np.float64(nx))
    return s, np.divide(iy + uniform(key, dim, 2 * k + 1), np.float64(ny))


# Taylor coefficients of sin x / x and cos x in x^2: on [-pi/4, pi/4] the first terms left out are below 1e-15
S1, S2, S3, S4, S5, S6, S7 = (
    -1.0 / 6,
    1.0 / 120,
    -1.0 / 5040,
    1.0 / 362880,
    -1.0 / 39916800,
    1.0 / 6227020800,
    -1.0 / 1307674368000,
)
C1, C2, C3, C4, C5, C6, C7, C8 = (
    -0.5,
    1.0 / 24,
    -1.0 / 720,
    1.0 / 40320,
    -1.0 / 3628800,
    1.0 / 479001600,
    -1.0 / 87178291200,
    1.0 / 20922789888000,
)


@inline
def sincos_turn(t):
    """(sin, cos) of 2 pi t, t in [0, 1], within 1e-15 of libm's: the quarter turn is taken from t exactly and the
    rest, within an eighth of a turn, goes to polynomials, with selects for the quadrant. libm's sin and cos took 11
    ns a call, a third of the cost of making an AO ray."""
    u = 4.0 * t
    q = math.floor(u + 0.5)
    x = (u - q) * (0.5 * math.pi)
    x2 = x * x
    sp = x * (1.0 + x2 * (S1 + x2 * (S2 + x2 * (S3 + x2 * (S4 + x2 * (S5 + x2 * (S6 + x2 * S7)))))))
    cp = 1.0 + x2 * (C1 + x2 * (C2 + x2 * (C3 + x2 * (C4 + x2 * (C5 + x2 * (C6 + x2 * (C7 + x2 * C8)))))))
    quadrant = int(q) & 3
    sine = cp if quadrant & 1 else sp
    cosine = sp if quadrant & 1 else cp
    return (-sine if quadrant & 2 else sine), (-cosine if (quadrant + 1) & 2 else cosine)


@inline
def tangent_frame(nx, ny, nz):
    """Two unit vectors that complete unit normal n to an orthonormal basis (Duff et al. 2017): once per hit, not per
    ray (its sign's branch and division made a third of an AO ray's cost on varied normals)."""
    sign = 1.0 if nz >= 0.0 else -1.0
    a = -1.0 / (sign + nz)
    b = nx * ny * a
    return (1.0 + sign * nx * nx * a, sign * b, -sign * nx), (b, sign + ny * ny * a, -ny)


@inline
def cosine_hemisphere(n, tangent, bitangent, s, t):
    """Cosine-weighted direction about unit normal n, given its tangent_frame, from a point (s, t) of the unit
    square."""
    r = math.sqrt(max(s, 0.0))  # s >= 0: the max tells LLVM so, which then takes the sqrt instruction, not libm's
    sine, cosine = sincos_turn(t)
    lx, ly, lz = r * cosine, r * sine, math.sqrt(max(0.0, 1.0 - s))
    return (
        lx * tangent[0] + ly * bitangent[0] + lz * n[0],
        lx * tangent[1] + ly * bitangent[1] + lz * n[1],
        lx * tangent[2] + ly * bitangent[2] + lz * n[2],
    )


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
