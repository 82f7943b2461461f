"""weier16's resampling info (weier2016 section 3.3): the previous final colour reprojected through the coarse mesh
at the support resolution with section 3.2's footprint filter, and the cells whose depth or luminance departs from
their neighbourhood, or whose surface was seen at a grazing angle, marked to be traced afresh, where the
reprojection moved the cell or a neighbour or shows the support image's coarse reconstruction (elsewhere it shows
the previous frame's samples unchanged: no reprojection error to find)."""

from __future__ import annotations

import math

import numba as nb

from hmdrt.foveation.stages.reproject import ROWS, row_footprints
from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.optics.projection import bilinear3, view_point


@serial
def _footprint_mean(color, qx, qy, spread, taps):
    """Section 3.2's footprint filter of the previous final colour at (qx, qy), spread: the footprint's width in
    its pixels: bilinear about a pixel wide, else the mean of bilinear taps at offsets sigma = spread / 2 times
    `taps` (k, 2), one normally distributed pattern for every cell (no random numbers drawn per cell)."""
    if spread <= 1.5:
        return bilinear3(color, qx, qy)
    sigma, n = 0.5 * spread, taps.shape[0]
    r = g = b = 0.0
    for k in range(n):
        sr, sg, sb = bilinear3(color, qx + sigma * taps[k, 0], qy + sigma * taps[k, 1])
        r, g, b = r + sr, g + sg, b + sb
    return r / n, g / n, b / n


@inline
def _set_near(cells, y, x):
    """Whether cell (y, x) or one of its 4-neighbours is set: the cells a test at (y, x) reads (_discontinuous).
    Inlined, as _discontinuous is: a helper that takes an array and branches costs numba a reference count per call,
    shared by the threads (CONTRIBUTING.md, numba notes)."""
    h, w = cells.shape
    return (
        cells[y, x] != 0
        or (x > 0 and cells[y, x - 1] != 0)
        or (x + 1 < w and cells[y, x + 1] != 0)
        or (y > 0 and cells[y - 1, x] != 0)
        or (y + 1 < h and cells[y + 1, x] != 0)
    )


@serial
def _luminance_rows(y0, y1, prev, color, rule, scratch, tested):
    """Rows [y0, y1) of the reprojected final colour's luminance at the support resolution (section 3.3 renders
    the coarse mesh at that resolution with section 3.2's procedure), NaN where the mesh leaves a cell; only at
    the cells the tests read (_set_near a tested one: on a still view, those near the cells showing the support
    image), the others left as they were."""
    covered, lum = scratch.covered, scratch.lum
    h, w = lum.shape
    spread = scratch.footprints[nb.get_thread_id()]
    for y in range(y0, y1):
        row_footprints(prev, covered, 1, y, spread)
        for x in range(w):
            if not _set_near(tested, y, x):
                continue
            if not covered[y, x]:
                lum[y, x] = math.nan
                continue
            r, g, b = _footprint_mean(color, prev[0, y, x], prev[1, y, x], spread[x], rule.taps)
            lum[y, x] = 0.2126 * r + 0.7152 * g + 0.0722 * b


@serial
def _bent(a, b, c, eps):
    """Section 3.3's depth test along one axis: 1/z, affine across a plane in the image (the mesh interpolates
    it so), departs at b from the line through its neighbours a and c by more than eps of b's. A plane gives
    0 however slanted; a depth jump to one neighbour by more than eps of the depth trips it."""
    return abs(a - 2.0 * b + c) > eps * b


@serial
def _contrast(a, b, eps):
    """Section 3.3's luminance test between two cells: |a - b| / (a + b) above eps; NaN (uncovered) never."""
    return a + b > 0.0 and abs(a - b) > eps * (a + b)


@inline
def _discontinuous(zinv, covered, lum, y, x, rule):
    """Section 3.3: a depth or luminance difference between cell (y, x) and its direct neighbourhood in the
    reprojected image."""
    h, w = zinv.shape
    z = zinv[y, x]
    if (
        0 < x < w - 1
        and covered[y, x - 1]
        and covered[y, x + 1]
        and _bent(zinv[y, x - 1], z, zinv[y, x + 1], rule.depth)
    ):
        return True
    if (
        0 < y < h - 1
        and covered[y - 1, x]
        and covered[y + 1, x]
        and _bent(zinv[y - 1, x], z, zinv[y + 1, x], rule.depth)
    ):
        return True
    la = lum[y, x]
    return (
        (x + 1 < w and _contrast(la, lum[y, x + 1], rule.lum))
        or (x > 0 and _contrast(la, lum[y, x - 1], rule.lum))
        or (y + 1 < h and _contrast(la, lum[y + 1, x], rule.lum))
        or (y > 0 and _contrast(la, lum[y - 1, x], rule.lum))
    )


@serial
def _previous_cell(qx, qy, ph, pw, full_w, full_h):
    """The support cell (row, column) of a ph x pw support image over full_w x full_h pixels that held the surface
    seen in the previous frame at its pixel coordinates (qx, qy)."""
    sx = min(max(int(qx * pw / full_w), 0), pw - 1)
    sy = min(max(int(qy * ph / full_h), 0), ph - 1)
    return sy, sx


@inline
def _grazing(mesh, cur, normal, prev_position, x, y, full_w, full_h, eps):
    """Section 3.3's edge test: edge_t = max(n.d, 0) < eps with the previous frame's geometric normal n and the
    direction d to its eye, at cell (y, x); never where the support G-buffer holds no normal (a miss)."""
    sy, sx = _previous_cell(mesh.prev[0, y, x], mesh.prev[1, y, x], normal.shape[0], normal.shape[1], full_w, full_h)
    nx, ny, nz = normal[sy, sx, 0], normal[sy, sx, 1], normal[sy, sx, 2]
    if nx == 0.0 and ny == 0.0 and nz == 0.0:
        return False
    px, py, pz = view_point(cur, x + 0.5, y + 0.5, 1.0 / mesh.zinv[y, x])
    vx, vy, vz = prev_position[0] - px, prev_position[1] - py, prev_position[2] - pz
    inv = 1.0 / max(math.sqrt(vx * vx + vy * vy + vz * vz), 1e-30)
    return max((nx * vx + ny * vy + nz * vz) * inv, 0.0) < eps


@kernel
def _resampling_info(mesh, cur, color, normal, unsampled, prev_position, full_w, full_h, rule, scratch, out):
    """weier2016 section 3.3 at support resolution: the previous final colour reprojected through the coarse
    mesh; cells with a depth or luminance discontinuity against their neighbourhood or a grazing surface are
    marked where the reprojected image may be wrong: where the reprojection moved them or a neighbour by more
    than rule.motion full-resolution pixels, or where it shows the coarse support image's reconstruction
    (`unsampled`, cells of the previous frame: cache._unsampled_cells). Uncovered cells are not: section 3.3
    reconstructs them from the support image (the merge)."""
    # written through locals: see hmdrt/trace/blocks.py
    zinv, prev, covered, moved = mesh.zinv, mesh.prev, scratch.covered, scratch.moved
    h, w = zinv.shape
    cell_w, cell_h = full_w / w, full_h / h
    for y in nb.prange(h):
        for x in range(w):
            on = zinv[y, x] > 0.0
            covered[y, x] = 1 if on else 0
            shift = max(abs(prev[0, y, x] - (x + 0.5) * cell_w), abs(prev[1, y, x] - (y + 0.5) * cell_h))
            moved[y, x] = 1 if on and shift > rule.motion else 0
    ph, pw = unsampled.shape
    for y in nb.prange(h):
        for x in range(w):
            tested = False
            if covered[y, x] != 0:
                sy, sx = _previous_cell(prev[0, y, x], prev[1, y, x], ph, pw, full_w, full_h)
                tested = _set_near(moved, y, x) or unsampled[sy, sx] != 0  # it or a neighbour moved
            out[y, x] = tested  # the cells tested, then (below) those the tests mark
    for b in nb.prange((h + ROWS - 1) // ROWS):
        _luminance_rows(b * ROWS, min(h, (b + 1) * ROWS), prev, color, rule, scratch, out)
    lum = scratch.lum
    for y in nb.prange(h):
        for x in range(w):
            out[y, x] = out[y, x] and (
                _discontinuous(zinv, covered, lum, y, x, rule)
                or _grazing(mesh, cur, normal, prev_position, x, y, full_w, full_h, rule.edge)
            )
