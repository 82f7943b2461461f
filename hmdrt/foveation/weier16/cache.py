"""weier16's cache update (weier2016 sections 3.2 and 3.4): the support image and support G-buffer extracted from
the frame's samples, then one pass: the previous frame gathered through the coarse mesh with its footprint filter,
each new sample (the support pixels' among them) merged into the cache with the running estimate or replacing
it, and the pixels left without colour merged from the support image."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from hmdrt.foveation.stages.reproject import ROWS, gaussian_taps, nearest_texel, row_footprints
from hmdrt.foveation.stages.temporal import k_at, running_estimate
from hmdrt.foveation.weier16.buffers import cell_span
from hmdrt.foveation.weier16.params import COVERED, FRESH, INFO, SHOWN, TRACED
from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.schedule import claim
from hmdrt.optics.projection import FAR, bilinear3, bilinear_footprint, blend_footprint, view_distance


@inline
def _moved(depth, dist, eps_cache):
    """Section 3.4: the sample's surface is not the cached one: one of them a miss and the other not, or
    their distances from the eye apart by more than eps_cache of the sample's."""
    far_sample, far_cache = depth >= FAR or math.isinf(depth), dist >= 0.5 * FAR
    return far_sample != far_cache or (not far_sample and abs(dist - depth) > eps_cache * depth)


@kernel
def _gather_support(grid, index, samples, normals, support):
    """Section 3.4: the support image and support G-buffer "extracted" from the frame's samples, each support
    pixel's own (grid: where they lie; index: each traced pixel's sample); a support row per task."""
    depth, normal, color, light = support.depth, support.normal, support.color, support.light
    for j in nb.prange(grid.y.shape[0]):
        y = int(grid.y[j])
        for i in range(grid.x.shape[0]):
            s = index[y, int(grid.x[i])]
            depth[j, i] = samples.depth[s]
            for c in range(3):
                normal[j, i, c] = normals[s, c]
                color[j, i, c] = samples.rgb[s, c]
                light[j, i, c] = samples.light[s, c]


@kernel
def _unsampled_cells(flags, unsampled, rows):
    """The support cells (those of the resampling info: pixel (y, x) in cell (y sh // h, x sw // w)) holding a
    pixel flagged SHOWN by the cache update: covered by the reprojection but showing the support image's
    reconstruction, no sample of its own (rho 0: merged when it was uncovered, untraced since). Section 3.3
    reconstructs such pixels from the coarse support image; the next frame's resampling info tests these cells
    for the discontinuities it misses. A cell row per task: its pixel rows OR-ed into one (a loop that
    vectorises, in `rows`, a row of scratch per numba thread), then each cell's span of that row."""
    h, w = flags.shape
    sh, sw = unsampled.shape
    for j in nb.prange(sh):
        y0, y1 = cell_span(np.int64(j), h, sh)
        row = rows[nb.get_thread_id()]
        for x in range(w):
            row[x] = flags[y0, x]
        for y in range(y0 + 1, y1):
            for x in range(w):
                row[x] |= flags[y, x]
        for i in range(sw):
            x0, x1 = cell_span(i, w, sw)
            shown = np.uint8(0)
            for x in range(x0, x1):
                shown |= row[x]
            unsampled[j, i] = (shown & SHOWN) != 0


@serial
def _shown(f, rho):
    """Flags f of a covered pixel left untraced, with SHOWN set where its cache info (rho) holds no sample."""
    return f | (np.uint8(SHOWN) if rho <= 0.0 else np.uint8(0))


@inline
def _merge_support(y, x, support, grid, rule, final):
    """Section 3.4's merge at pixel (y, x), which nothing covers: the bilinearly upsampled support image, colour
    and light buffer, with no sample counted."""
    color, info = final.color, final.info
    color[y, x, 0], color[y, x, 1], color[y, x, 2] = bilinear3(support.color, grid.u[x], grid.v[y])
    for c in range(INFO):
        info[y, x, c] = 0.0
    if rule.stochastic:
        final.light[y, x, 0], final.light[y, x, 1], final.light[y, x, 2] = bilinear3(
            support.light, grid.u[x], grid.v[y]
        )


@serial
def _update_rows(y0, y1, selection, mesh, cur, previous, samples, support, grid, rule, taps, final, image):
    flags, row_start = selection.flags, selection.row_start
    prev, zinv = mesh.prev, mesh.zinv
    prev_color, prev_info, prev_light = previous.color, previous.info, previous.light
    rgb, sample_depth, sample_light = samples.rgb, samples.depth, samples.light
    color, info, light = final.color, final.info, final.light
    h, w = flags.shape
    t = nb.get_thread_id()
    spread_row, across, down = taps.spread[t], taps.weights[t, 0], taps.weights[t, 1]
    corner, step_x, step_y = taps.index[t, 0], taps.index[t, 1], taps.index[t, 2]
    flat = prev_color.reshape(-1)
    history = zinv.shape[0] == h  # else no pixel is covered, and the mesh buffers may be empty
    for y in range(y0, y1):
        if history:
            row_footprints(prev, flags, COVERED, y, spread_row)
            px, py = prev[0, y], prev[1, y]
            for x in range(w):
                across[x], down[x], corner[x], step_x[x], step_y[x] = bilinear_footprint(px[x], py[x], w, h)
        s = row_start[y]
        merged = 0
        for x in range(w):
            f = flags[y, x]
            covered, traced = (f & COVERED) != 0, (f & TRACED) != 0
            new = traced and (
                (f & FRESH) != 0
                or not covered
                or _moved(
                    sample_depth[s], np.float32(view_distance(cur, x + 0.5, y + 0.5, 1.0 / zinv[y, x])), rule.eps_cache
                )
            )
            r = g = b = 0.0
            jy = jx = 0
            if covered and not new:  # the previous frame seen through the mesh
                qx, qy, spread = prev[0, y, x], prev[1, y, x], spread_row[x]
                if spread <= 1.5 or rule.footprint_samples <= 1:
                    r, g, b = blend_footprint(flat, corner[x], step_x[x], step_y[x], across[x], down[x])
                else:
                    key = (y * w + x) * 64 + rule.seed
                    r, g, b = gaussian_taps(prev_color, qx, qy, 0.5 * spread, rule.footprint_samples, key)
                r, g, b = np.float32(r), np.float32(g), np.float32(b)  # the reprojected image is float32
                jy, jx = nearest_texel(qx, qy, w, h)  # cache info is not blended: the nearest texel
            if traced:
                alpha, rho = 1.0, 1.0
                if not new:
                    k = k_at(rule.ages, rule.frame - prev_info[jy, jx, 2], rule.k_min, rule.k_max, rule.t_max)
                    # rho 0: merged from the support image, no sample of this pixel; the new one replaces it
                    alpha, rho = running_estimate(prev_info[jy, jx, 1], k)
                color[y, x, 0] = alpha * rgb[s, 0] + (1.0 - alpha) * r
                color[y, x, 1] = alpha * rgb[s, 1] + (1.0 - alpha) * g
                color[y, x, 2] = alpha * rgb[s, 2] + (1.0 - alpha) * b
                info[y, x, 0], info[y, x, 1], info[y, x, 2] = alpha, rho, rule.frame
                if rule.stochastic:
                    for c in range(3):
                        kept = 0.0 if new else prev_light[jy, jx, c]
                        light[y, x, c] = alpha * sample_light[s, c] + (1.0 - alpha) * kept
                s += 1
            elif covered:
                color[y, x, 0], color[y, x, 1], color[y, x, 2] = r, g, b
                for c in range(INFO):
                    info[y, x, c] = prev_info[jy, jx, c]
                flags[y, x] = _shown(f, prev_info[jy, jx, 1])
                if rule.stochastic:
                    for c in range(3):
                        light[y, x, c] = prev_light[jy, jx, c]
            else:
                _merge_support(y, x, support, grid, rule, final)
                merged += 1
            for c in range(3):
                image[y, x, c] = color[y, x, c]
        selection.merged[y] = merged


@serial
def _update_rows_in_place(y0, y1, selection, distance, samples, support, grid, rule, final, image):
    """_update_rows where the mesh reprojects every covered pixel onto its own texel and `final` is the previous
    frame: a covered pixel without a sample keeps what it holds, a traced one merges with its own texel, whose
    surface lies at the mesh's `distance` (CoarseMesh.distances, measured once while the view holds still);
    the rows then copied into the image in a loop of their own."""
    flags, row_start, color, info, light = selection.flags, selection.row_start, final.color, final.info, final.light
    w = flags.shape[1]
    for y in range(y0, y1):
        s = row_start[y]
        merged = 0
        for x in range(w):
            f = flags[y, x]
            covered = (f & COVERED) != 0
            if f & TRACED:  # the sample merged into the pixel's own colour and cache info, or replacing them
                new = (f & FRESH) != 0 or not covered or _moved(samples.depth[s], distance[y, x], rule.eps_cache)
                alpha, rho = 1.0, 1.0
                if not new:
                    k = k_at(rule.ages, rule.frame - info[y, x, 2], rule.k_min, rule.k_max, rule.t_max)
                    alpha, rho = running_estimate(info[y, x, 1], k)
                for c in range(3):
                    kept = np.float32(0.0) if new else color[y, x, c]
                    color[y, x, c] = alpha * samples.rgb[s, c] + (1.0 - alpha) * kept
                info[y, x, 0], info[y, x, 1], info[y, x, 2] = alpha, rho, rule.frame
                if rule.stochastic:
                    for c in range(3):
                        kept = np.float32(0.0) if new else light[y, x, c]
                        light[y, x, c] = alpha * samples.light[s, c] + (1.0 - alpha) * kept
                s += 1
            elif covered:
                flags[y, x] = _shown(f, info[y, x, 1])
            else:
                _merge_support(y, x, support, grid, rule, final)
                merged += 1
        selection.merged[y] = merged
    rows, colors = image[y0:y1].reshape(-1), color[y0:y1].reshape(-1)
    for i in range(rows.shape[0]):
        rows[i] = colors[i]


@kernel
def _update(
    selection, mesh, cur, distance, previous, samples, support, grid, rule, taps, final, image, counter, threads
):
    """Sections 3.2 and 3.4 in one pass: each pixel's previous colour and cache info gathered through the
    mesh, its sample (a support pixel's too) merged into them with the running estimate (or replacing them:
    fovea, resampled, uncovered or moved), and pixels left without colour taken from the support image
    (support, at grid's coordinates); into the final colour, cache info and the caller's image. In place
    (rule.in_place: final is previous, the mesh reprojecting each pixel onto its own texel), covered pixels
    without a sample keep what they hold."""
    h = selection.flags.shape[0]
    blocks = (h + ROWS - 1) // ROWS
    for _ in nb.prange(threads):
        b = claim(counter)
        while b < blocks:
            y0, y1 = b * ROWS, min(h, (b + 1) * ROWS)
            if rule.in_place:
                _update_rows_in_place(y0, y1, selection, distance, samples, support, grid, rule, final, image)
            else:
                _update_rows(y0, y1, selection, mesh, cur, previous, samples, support, grid, rule, taps, final, image)
            b = claim(counter)
