"""Texture lookup: checkerboard, fractal noise and bilinear image maps.

Texture coordinates are (u, v, 0) for UV-mapped surfaces and the world position for world-mapped
ones; the surface pass chooses, this pass turns them into albedo = diffuse x texture.
"""

import math

import numpy as np

from hmdrt.kernels.jit import inline, serial
from hmdrt.scene.noise import fbm_rows
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
def texture_block(mats, material, coords, active, albedo, lookup, lookup_ids, start, stop):
    """albedo[i] = diffuse x texture of material[i] at coords[i], for active i in [start, stop). Image lookups are
    calls, not inlined: their code in the loop would slow the common checker and plain cases. Noise lookups are
    listed in `lookup` and `lookup_ids` ((4, n) float64 and (3, n) int64 scratch: noise.fbm_rows) and computed
    together after the loop, where the fractal sums vectorise."""
    diffuse, kinds, scales = mats.diffuse, mats.tex_kind, mats.tex_scale
    c0, c1, octaves, seeds = mats.tex_color0, mats.tex_color1, mats.tex_octaves, mats.tex_seed
    texels, offsets, heights, widths = mats.texels, mats.tex_offset, mats.tex_height, mats.tex_width
    m = most = 0
    for i in range(start, stop):
        i = np.uint64(i)  # unsigned indices: no negative-index wraparound on the loads
        if not active[i]:
            continue
        k = np.uint64(material[i])
        kind = kinds[k]
        s = scales[k]
        a, b, c = coords[i, 0] * s, coords[i, 1] * s, coords[i, 2] * s
        if kind == TEX_NOISE:
            lookup[0, m], lookup[1, m], lookup[2, m] = a, b, c
            lookup_ids[0, m], lookup_ids[1, m], lookup_ids[2, m] = i, octaves[k], seeds[k]
            most = max(most, octaves[k])
            m += 1
            continue
        if kind == TEX_IMAGE:
            _bilinear(texels, offsets[k], heights[k], widths[k], a, b, albedo, i)
        elif kind == TEX_CHECKER:
            t = float((int(math.floor(a)) + int(math.floor(b)) + int(math.floor(c))) & 1)
            _blend(c0, c1, k, t, albedo, i)
        else:
            for ch in range(3):
                albedo[i, ch] = 1.0
        for ch in range(3):
            albedo[i, ch] *= diffuse[k, ch]
    if m == 0:
        return
    fbm_rows(lookup, lookup_ids, m, most)
    for q in range(m):
        i = lookup_ids[0, q]
        k = material[i]
        _blend(c0, c1, k, min(max(0.5 + 0.5 * lookup[3, q], 0.0), 1.0), albedo, i)
        for ch in range(3):
            albedo[i, ch] *= diffuse[k, ch]


@inline
def _blend(c0, c1, k, t, albedo, i):
    for ch in range(3):
        albedo[i, ch] = (1.0 - t) * c0[k, ch] + t * c1[k, ch]  # exact at t = 0 and t = 1


def sample_texture(mats: Materials, material: int, coords: np.ndarray) -> np.ndarray:
    """Albedo (n, 3) of one material at texture coordinates (n, 3): (u, v, 0) or world points."""
    n = len(coords)
    out = np.empty((n, 3), np.float32)
    material_ = np.full(n, material, np.int32)
    coords = np.ascontiguousarray(coords, np.float64)
    texture_block(mats, material_, coords, np.ones(n, bool), out, np.empty((4, n)), np.empty((3, n), np.int64), 0, n)
    return out
