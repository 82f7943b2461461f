"""Texture lookup: checkerboard, fractal noise and bilinear image maps.

Texture coordinates are (u, v, 0) for UV-mapped surfaces and the world position for world-mapped
ones; the surface pass chooses, this pass turns them into albedo = diffuse x texture.
"""

import math

import numpy as np

from hmdrt.kernels.jit import serial
from hmdrt.scene.noise import fbm
from hmdrt.scene.pack import TEX_CHECKER, TEX_IMAGE, TEX_NOISE, Materials


@serial
def _bilinear(texels, base, h, w, u, v, out, i):
    x = (u - math.floor(u)) * w - 0.5
    y = (1.0 - (v - math.floor(v))) * h - 0.5  # UV origin is the bottom-left of the image
    x0, y0 = math.floor(x), math.floor(y)
    fx, fy = x - x0, y - y0
    ix, iy = int(x0), int(y0)
    for c in range(3):
        out[i, c] = 0.0
    for dy in range(2):
        row = (iy + dy) % h
        wy = fy if dy else 1.0 - fy
        for dx in range(2):
            idx = base + row * w + (ix + dx) % w
            wgt = (fx if dx else 1.0 - fx) * wy
            for c in range(3):
                out[i, c] += wgt * texels[idx, c]


@serial
def _noise(a, b, c, octaves, seed):
    return min(max(0.5 + 0.5 * fbm(a, b, c, octaves, seed), 0.0), 1.0)


@serial
def texture_block(mats, material, coords, active, albedo, start, stop):
    """albedo[i] = diffuse x texture of material[i] at coords[i], for active i in [start, stop). Image and noise
    lookups are calls, not inlined: their code in the loop would slow the common checker and plain cases."""
    diffuse, kinds, scales = mats.diffuse, mats.tex_kind, mats.tex_scale
    c0, c1, octaves, seeds = mats.tex_color0, mats.tex_color1, mats.tex_octaves, mats.tex_seed
    texels, offsets, heights, widths = mats.texels, mats.tex_offset, mats.tex_height, mats.tex_width
    for i in range(start, stop):
        if not active[i]:
            continue
        k = material[i]
        kind = kinds[k]
        s = scales[k]
        a, b, c = coords[i, 0] * s, coords[i, 1] * s, coords[i, 2] * s
        if kind == TEX_IMAGE:
            _bilinear(texels, offsets[k], heights[k], widths[k], a, b, albedo, i)
        elif kind == TEX_CHECKER or kind == TEX_NOISE:
            if kind == TEX_CHECKER:
                t = float((int(math.floor(a)) + int(math.floor(b)) + int(math.floor(c))) & 1)
            else:
                t = _noise(a, b, c, octaves[k], seeds[k])
            for ch in range(3):
                albedo[i, ch] = (1.0 - t) * c0[k, ch] + t * c1[k, ch]  # exact at t = 0 and t = 1
        else:
            for ch in range(3):
                albedo[i, ch] = 1.0
        for ch in range(3):
            albedo[i, ch] *= diffuse[k, ch]


def sample_texture(mats: Materials, material: int, coords: np.ndarray) -> np.ndarray:
    """Albedo (n, 3) of one material at texture coordinates (n, 3): (u, v, 0) or world points."""
    n = len(coords)
    out = np.empty((n, 3), np.float32)
    texture_block(
        mats, np.full(n, material, np.int32), np.ascontiguousarray(coords, np.float64), np.ones(n, bool), out, 0, n
    )
    return out
