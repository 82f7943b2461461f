"""kim21's selective supersampling (kim2021 section 4.6.2 and Figure 2): stratified jittered extra samples in each
problematic subpixel, (n_f, n_p, n_m, n_np) by band, then each rendered central pixel the mean of its four
subpixels, the others interpolated from the four surrounding pixel centres (or, as Jin et al., presampled)."""

from __future__ import annotations

import numba as nb
import numpy as np

from hmdrt.kernels.jit import kernel, serial
from hmdrt.kernels.schedule import claim
from hmdrt.optics.projection import bilinear3
from hmdrt.trace.sampling import DIM_PIXEL, grid_dims, stratified

MAX_SUBPIXEL_SAMPLES = 16


@serial
def _exclusive_scan(counts):
    """counts[k] becomes the sum of counts[:k], in place; returns the total."""
    total = 0
    for k in range(counts.shape[0]):
        c = counts[k]
        counts[k] = total
        total += c
    return total


@serial
def _subpixel_samples_row(y, width, sub_mask, samples, spans, first, seed_key, xy, keys):
    j = first[y]
    for x in range(spans[y, 0], spans[y, 1]):
        i = y * width + x
        m = sub_mask[i]
        if m == 0:
            continue
        n = np.int64(samples[i])
        nx, ny = grid_dims(n)
        for s in range(4):
            if not (m >> s) & 1:
                continue
            ox, oy = x + 0.5 * (s & 1), y + 0.5 * (s >> 1)
            key = (i * 4 + s) * MAX_SUBPIXEL_SAMPLES + seed_key
            for k in range(n):
                sx, sy = stratified(key, k, DIM_PIXEL, nx, ny)
                xy[j, 0] = ox + 0.5 * sx
                xy[j, 1] = oy + 0.5 * sy
                keys[j] = key + k
                j += 1


@kernel
def _subpixel_samples(width, sub_mask, samples, spans, first, seed_key, xy, keys):
    """Stratified jittered positions of the extra samples, subpixel by subpixel in scanline order (section 4.6.2);
    row y's start at first[y]. seed_key is the frame's (kim21.method), so the jitter changes from frame to frame.
    sub_mask is read in each row's central columns (spans: Foveation.spans), where the inspection wrote it."""
    for y in nb.prange(first.shape[0] - 1):
        _subpixel_samples_row(np.uint64(y), width, sub_mask, samples, spans, first, seed_key, xy, keys)


@serial
def _mean3(rows, start, count):
    """The mean of rows [start, start + count) of an (n, 3) array."""
    r = g = b = 0.0
    for j in range(start, start + count):
        r, g, b = r + rows[j, 0], g + rows[j, 1], b + rows[j, 2]
    return r / count, g / count, b / count


@serial
def _tent(up, mid, down, x, ch):
    """Channel ch of the mean of pixel x's four subpixels, each interpolated from the four surrounding pixel
    centres (kim2021 Figure 2), given its row and the rows above and below (w, 3), clamped at the border as
    bilinear3 is: bilinear weights 3/4 and 1/4 per axis average to (1, 6, 1) / 8 over the 3 x 3 neighbourhood."""
    a, c = np.float32(0.125), np.float32(0.75)
    xl, xr = max(x - 1, 0), min(x + 1, mid.shape[0] - 1)
    left = a * (up[xl, ch] + down[xl, ch]) + c * mid[xl, ch]
    centre = a * (up[x, ch] + down[x, ch]) + c * mid[x, ch]
    right = a * (up[xr, ch] + down[xr, ch]) + c * mid[xr, ch]
    return a * (left + right) + c * centre


@serial
def _subpixel_color(image, x, y, s, interpolate):
    """Subpixel s (NW, NE, SW, SE) of pixel (x, y) when not problematic: interpolated at its centre from the four
    surrounding pixel centres (kim2021 Figure 2), or the pixel's presampled colour (Jin et al.)."""
    if interpolate:
        return bilinear3(image, x + 0.25 + 0.5 * (s & 1), y + 0.25 + 0.5 * (s >> 1))
    return np.float64(image[y, x, 0]), np.float64(image[y, x, 1]), np.float64(image[y, x, 2])


@serial
def _resolve_row(y, image, sub_mask, samples, spans, flags, first, extra, interpolate, out):
    height, width, y = image.shape[0], image.shape[1], np.int64(y)
    up, mid, down = image[max(y - 1, 0)], image[y], image[min(y + 1, height - 1)]
    j = first[y]
    for x in range(spans[y, 0], spans[y, 1]):
        i = y * width + x
        if samples[i] == 0 or flags[i] != 0:
            continue
        m, k = sub_mask[i], np.int64(samples[i])
        if m == 0:
            for ch in range(3 if interpolate else 0):
                out[i, ch] = _tent(up, mid, down, x, ch)
            continue
        r = g = b = 0.0
        for s in range(4):
            if (m >> s) & 1:
                cr, cg, cb = _mean3(extra, j, k)
                j += k
            else:
                cr, cg, cb = _subpixel_color(image, x, y, s, interpolate)
            r, g, b = r + cr, g + cg, b + cb
        out[i, 0], out[i, 1], out[i, 2] = 0.25 * r, 0.25 * g, 0.25 * b


@kernel
def _resolve(image, sub_mask, samples, spans, flags, first, extra, interpolate, out, counter, threads):
    """Section 4.6.2 and Figure 2: each central pixel that was rendered (flags 0) is the mean of its four subpixels,
    a problematic one the mean of its extra samples, the others their _subpixel_color from the presampled colours
    (image, (h, w, 3)); out already holds the presampled colour, which stays where nothing is interpolated. Each
    row's central columns (spans: Foveation.spans) alone."""
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < image.shape[0]:
            _resolve_row(y, image, sub_mask, samples, spans, flags, first, extra, interpolate, out)
            y = claim(counter)
