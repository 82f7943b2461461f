"""weier16's ray generation (weier2016 section 3.1): the pixels traced this frame, by the foveal probability, the
resampling info and the support image's pixels, and the tracer's sample list, one sample per traced pixel."""

from __future__ import annotations

import numba as nb
import numpy as np

from hmdrt.foveation.stages.sampling import foveal_probability
from hmdrt.foveation.weier16.buffers import cell_span
from hmdrt.foveation.weier16.params import COVERED, FOVEA, FRESH, RESAMPLE, SUPPORT, TRACED
from hmdrt.kernels.jit import kernel
from hmdrt.kernels.rng import uniform
from hmdrt.kernels.schedule import claim


@kernel
def _select(ecc, foveal, seed, frame, zinv, resample, grid, selection, draws, counter, threads):
    """Section 3.1's ray generation (pixel q traced when xi_q < p(q), sampling.bernoulli_mask's xi), the pixels
    of cells marked in the resampling info and the support image's pixels (grid, always traced, once), with each
    pixel's flags and each row's sample count. A row is a pass each: its xi and the flags that depend on the pixel
    alone (loops of selects that vectorise), then, where there is a history, the mesh's coverage and the pixels
    of the resampling info's marked cells OR-ed in, and the count."""
    flags, counts, resampled = selection.flags, selection.counts, selection.resampled
    h, w = flags.shape
    sh, sw = resample.shape
    history = zinv.shape[0] == h
    r0, r1, p_min = foveal
    fovea_flags, support_flags = np.uint8(FOVEA | TRACED | FRESH), np.uint8(TRACED | SUPPORT)
    fresh, covered, traced = np.uint8(TRACED | FRESH | RESAMPLE), np.uint8(COVERED), np.uint8(TRACED)
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < h:
            xi, key = draws[nb.get_thread_id()], y * w + (seed << 32)
            for x in range(w):
                xi[x] = uniform(key + x, 0x5A3, frame)
            e_row, row, columns = ecc[y], flags[y], grid.column
            support_row = grid.row[y] >= 0
            for x in range(w):
                e = e_row[x]
                f = fovea_flags if e < r0 else np.uint8(0)
                p = foveal_probability(e, r0, r1, p_min)
                f |= traced if (p >= 1.0) | (xi[x] < p) else np.uint8(0)
                f |= support_flags if support_row & (columns[x] >= 0) else np.uint8(0)
                row[x] = f
            if history:
                z_row = zinv[y]
                for x in range(w):
                    row[x] |= covered if z_row[x] > 0.0 else np.uint8(0)
            nr = 0
            if sh > 0:
                marked = resample[y * sh // h]
                for i in range(sw):
                    if marked[i]:
                        x0, x1 = cell_span(i, w, sw)
                        for x in range(x0, x1):
                            row[x] |= fresh
                        nr += x1 - x0
            n = 0
            for x in range(w):
                n += row[x] & traced
            counts[y] = n
            resampled[y] = nr
            y = claim(counter)


@kernel
def _fill_samples(flags, row_start, key_base, xy, keys, index, listed):
    """Pixel centres and random-stream keys (base.pixel_keys, stream 0) of the traced pixels in scanline order;
    each traced pixel's sample in index. A row's traced columns are listed first, without a branch (`listed`: a
    row of scratch per numba thread), then filled: a branch per pixel mispredicts where the periphery traces at
    random (the kernel took 1.3-1.35x as long)."""
    h, w = flags.shape
    for y in nb.prange(h):
        columns = listed[nb.get_thread_id()]
        n = 0
        for x in range(w):
            columns[n] = x
            n += flags[y, x] & TRACED
        s = row_start[y]
        for m in range(n):
            x = columns[m]
            xy[s + m, 0], xy[s + m, 1] = x + 0.5, y + 0.5
            keys[s + m] = y * w + x + key_base
            index[y, x] = s + m
