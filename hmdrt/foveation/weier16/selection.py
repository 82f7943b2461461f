"""weier16's ray generation (weier2016 section 3.1): the pixels traced this frame, by the foveal probability, the
resampling info and the support image's pixels, and the tracer's sample list, one sample per traced pixel."""

from __future__ import annotations

import numba as nb

from hmdrt.foveation.stages.sampling import foveal_probability
from hmdrt.foveation.weier16.params import COVERED, FOVEA, FRESH, RESAMPLE, SUPPORT, TRACED
from hmdrt.kernels.jit import kernel
from hmdrt.kernels.rng import uniform
from hmdrt.kernels.schedule import claim


@kernel
def _select(ecc, foveal, seed, frame, zinv, resample, low_cols, grid, selection, draws, counter, threads):
    """Section 3.1's ray generation (pixel q traced when xi_q < p(q), sampling.bernoulli_mask's xi), the pixels
    of cells marked in the resampling info and the support image's pixels (grid, always traced, once), with each
    pixel's flags and each row's sample count. The row's xi are drawn first, in a loop of their own that
    vectorises, into the thread's row of `draws`."""
    flags, counts, resampled = selection.flags, selection.counts, selection.resampled
    h, w = flags.shape
    sh = resample.shape[0]
    history = zinv.shape[0] == h
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < h:
            xi, key = draws[nb.get_thread_id()], y * w + (seed << 32)
            for x in range(w):
                xi[x] = uniform(key + x, 0x5A3, frame)
            ly, support_row = y * sh // h, grid.row[y] >= 0
            n = nr = 0
            for x in range(w):
                e = ecc[y, x]
                f = COVERED if history and zinv[y, x] > 0.0 else 0
                if e < foveal.r0:
                    f |= FOVEA
                if sh > 0 and resample[ly, low_cols[x]]:
                    f |= TRACED | FRESH | RESAMPLE
                    nr += 1
                elif e < foveal.r0:  # p(q) = 1
                    f |= TRACED | FRESH
                else:
                    p = foveal_probability(e, foveal.r0, foveal.r1, foveal.p_min)
                    if p >= 1.0 or xi[x] < p:
                        f |= TRACED
                if support_row and grid.column[x] >= 0:
                    f |= TRACED | SUPPORT
                flags[y, x] = f
                n += f & TRACED
            counts[y] = n
            resampled[y] = nr
            y = claim(counter)


@kernel
def _fill_samples(flags, row_start, key_base, xy, keys, index):
    """Pixel centres and random-stream keys (base.pixel_keys, stream 0) of the traced pixels in scanline order;
    each traced pixel's sample in index."""
    h, w = flags.shape
    for y in nb.prange(h):
        s = row_start[y]
        for x in range(w):
            if flags[y, x] & TRACED:
                xy[s, 0], xy[s, 1] = x + 0.5, y + 0.5
                keys[s] = y * w + x + key_base
                index[y, x] = s
                s += 1
