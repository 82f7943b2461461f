"""Seeded 3D gradient noise and its fractal sum, shared by noise textures and displaced geometry."""

import math

import numba as nb
import numpy as np

from hmdrt.kernels.jit import inline, kernel
from hmdrt.kernels.rng import hash32
from hmdrt.scene.model import MAX_OCTAVES


@inline
def _grad(h, x, y, z):
    """Perlin's gradient of hash h dotted with (x, y, z), in selects: every operand is computed and picked, as the
    short-circuit `or` of the branching form made each of a corner's hashes a mispredicted jump (fbm 512 -> 181 ns
    a call, the same bits)."""
    h &= 15
    u = x if h < 8 else y
    xz = x if (h == 12) | (h == 14) else z
    v = y if h < 4 else xz
    return (-u if h & 1 else u) + (-v if h & 2 else v)


@inline
def _fade(t):
    return t * t * t * (t * (t * 6.0 - 15.0) + 10.0)


@inline
def gradient_noise(x: float, y: float, z: float, seed: int) -> float:
    """Improved-Perlin gradient noise in about [-1, 1], zero at lattice points."""
    xi, yi, zi = math.floor(x), math.floor(y), math.floor(z)
    fx, fy, fz = x - xi, y - yi, z - zi
    ix, iy, iz = int(xi), int(yi), int(zi)
    u, v, w = _fade(fx), _fade(fy), _fade(fz)
    acc = 0.0
    for c in range(8):
        dx, dy, dz = c & 1, (c >> 1) & 1, (c >> 2) & 1
        h = hash32(ix + dx, (iy + dy) * 7919 + (iz + dz) * 104729, seed)
        g = _grad(h, fx - dx, fy - dy, fz - dz)
        wx = u if dx else 1.0 - u
        wy = v if dy else 1.0 - v
        wz = w if dz else 1.0 - w
        acc += wx * wy * wz * g
    return acc


@inline
def fbm(x: float, y: float, z: float, octaves: int, seed: int) -> float:
    """Fractal sum of `octaves` noise octaves (lacunarity 2, gain 0.5), normalised to about [-1, 1]."""
    total, amp, norm, freq = 0.0, 1.0, 0.0, 1.0
    for o in range(octaves):
        total += amp * gradient_noise(x * freq, y * freq, z * freq, seed + o)
        norm += amp
        amp *= 0.5
        freq *= 2.0
    return total / norm


def _norms(most: int) -> np.ndarray:
    """fbm's normalisation for 0 .. most octaves, summed as fbm sums it."""
    norms, norm, amp = np.zeros(most + 1), 0.0, 1.0
    for o in range(most):
        norm += amp
        amp *= 0.5
        norms[o + 1] = norm
    return norms


_NORMS = _norms(MAX_OCTAVES)  # scene.pack refuses a noise texture with more octaves


@inline
def fbm_rows(points, ids, m, most):
    """fbm of each of the first m points of `points` ((4, n) float64: rows x, y and z, and a row the results
    go in) with its own octave count and seed (ids[1] and ids[2], (3, n) int64; at most `most` octaves), octave
    by octave so that the loop over the points vectorises: 29 against 206 ns a 4-octave fbm, the same bits (a
    point past its octaves adds 0.0 to a sum that is never -0.0)."""
    x, y, z, total = points[0], points[1], points[2], points[3]
    octaves, seeds = ids[1], ids[2]
    for i in range(m):
        total[i] = 0.0
    amp, freq = 1.0, 1.0
    for o in range(most):
        for i in range(m):
            g = amp * gradient_noise(x[i] * freq, y[i] * freq, z[i] * freq, seeds[i] + o)
            total[i] = total[i] + (g if o < octaves[i] else 0.0)
        amp *= 0.5
        freq *= 2.0
    for i in range(m):
        total[i] = total[i] / _NORMS[octaves[i]]


@kernel
def _fbm_points(points, octaves, seed, out):
    for i in nb.prange(points.shape[0]):
        out[i] = fbm(points[i, 0], points[i, 1], points[i, 2], octaves, seed)


def fbm_points(points: np.ndarray, octaves: int = 4, seed: int = 0) -> np.ndarray:
    """fbm at each of (n, 3) points, float64 (n,)."""
    out = np.empty(len(points), dtype=np.float64)
    _fbm_points(np.ascontiguousarray(points, dtype=np.float64), octaves, seed, out)
    return out
