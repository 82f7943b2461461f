"""Moving information between frames: back-projection of each pixel's hit into an earlier eye camera, and
weier2016's coarse mesh (section 3.2), which reprojects a whole earlier frame through its support G-buffer.

World points and their projections come from hmdrt.optics.projection; a miss (infinite depth) is a point at
infinity, so the sky reprojects by rotation alone. Used by kim2021 (sections 4.4, 4.7), weier2016
(section 3.2) and weier2018 (section 3.1, TAA).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.kernels.jit import inline, kernel, serial
from hmdrt.kernels.rng import uniform
from hmdrt.kernels.schedule import claim, dynamic
from hmdrt.optics.camera import EyeCamera
from hmdrt.optics.projection import (
    FAR,
    NEAR,
    CameraArrays,
    bilinear3,
    camera_arrays,
    pixel_of,
    project,
    project_view,
    to_eye,
    view_distance,
    world_point,
)


@kernel
def _backproject(cur, depth, prev, out_xy, out_dist):
    h, w = depth.shape
    for y in nb.prange(h):
        for x in range(w):
            px, py, pz = world_point(cur, x + 0.5, y + 0.5, depth[y, x])
            qx, qy, dist = project(prev, px, py, pz)
            out_xy[y, x, 0] = qx
            out_xy[y, x, 1] = qy
            out_dist[y, x] = dist if depth[y, x] < FAR else math.inf


def backproject(current: EyeCamera, depth: np.ndarray, previous: EyeCamera) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's first hit lies in an earlier camera: continuous pixel coordinates (h, w, 2)
    (NaN behind it) and the hit's distance from that camera (inf for a miss)."""
    h, w = depth.shape
    xy = np.empty((h, w, 2), np.float32)
    dist = np.empty((h, w), np.float32)
    _backproject(camera_arrays(current), np.ascontiguousarray(depth, np.float32), camera_arrays(previous), xy, dist)
    return xy, dist


# -- weier2016 section 3.2: reprojection through a coarse mesh built from the support G-buffer --

VERTEX_ATTRS = 4  # previous pixel x z, y z and z (z: previous view depth), each over the current view depth, and
# 1 over it: linear in the screen on a planar facet, so perspective-correct interpolation recovers x and y exactly
ROWS = 4  # rows of a block, the unit of work of the row-parallel kernels (see hmdrt/trace/blocks.py)
BANDS = 64  # bands of image rows the rasteriser splits the image into, one parallel task each
EDGE = 1e-9  # barycentric weight below 0 a pixel centre may have and be inside: a centre on an edge, as weier16's
# support pixels are (vertices on pixel centres) on a still view, is taken by both triangles whatever the rounding


class MeshVertices(NamedTuple):
    """The support grid's vertices in the current view and the attributes interpolated across them."""

    screen: np.ndarray  # (hs, ws, 3) float64: current pixel x, y and view depth
    attr: np.ndarray  # (hs, ws, VERTEX_ATTRS) float64


class CellRows(NamedTuple):
    """The image rows each cell of the grid can cover with its two triangles, and each row of cells: what a band of
    image rows needs to find its cells, in the mesh's order, without sorting them."""

    rows: np.ndarray  # (cells, 2) int64: the rows [r0, r1) the cell's triangles can cover, empty when both culled
    live: np.ndarray  # (cells,) uint8: bit t set where triangle t (_triangle) is not culled and covers a row
    spans: np.ndarray  # (hs - 1, 2) int64: the rows [r0, r1) the cells of a row of cells cover together
    band_rows: int


class MeshImage(NamedTuple):
    """The rasterised mesh per pixel: the previous frame's pixel coordinates of the surface seen there and
    its 1/z (current view depth), 0 where the mesh does not cover the pixel. The surface point itself lies
    on the pixel's view ray at depth 1/zinv (see view_point)."""

    prev: np.ndarray  # (2, h, w) float32: x and y planes
    zinv: np.ndarray  # (h, w) float32


@kernel
def _mesh_vertices(prev, grid_x, grid_y, depth, cur, frustums, screens, attr):
    """The grid's vertices in the current view, their pixel coordinates at each image size (frustums: the current
    camera's frustum over each, CameraArrays.frustum) and view depth into screens (sizes, hs, ws, 3): each vertex
    unprojected and its view ray divided once for every size, the same steps as project_view at each."""
    hs, ws = depth.shape
    for j in nb.prange(hs):
        for i in range(ws):
            px, py, pz = world_point(prev, grid_x[i], grid_y[j], depth[j, i])
            lx, ly, lz = to_eye(cur, px, py, pz)
            sz = -lz
            tx, ty = np.divide(lx, sz), np.divide(ly, sz)
            for k in range(frustums.shape[0]):
                sx, sy = pixel_of(frustums[k], tx, ty) if sz > NEAR else (0.0, 0.0)
                screens[k, j, i, 0], screens[k, j, i, 1], screens[k, j, i, 2] = sx, sy, sz
            zp = project_view(prev, px, py, pz)[2]
            iz = np.divide(1.0, sz) if sz > NEAR else 0.0  # a vertex at or behind the near plane culls its triangles
            attr[j, i, 0], attr[j, i, 1], attr[j, i, 2] = grid_x[i] * zp * iz, grid_y[j] * zp * iz, zp * iz
            attr[j, i, 3] = iz


@serial
def _triangle(j, i, t):
    """Grid vertices (row, column) of triangle t (0 or 1) of grid cell (j, i)."""
    if t == 0:
        return (j, i), (j, i + 1), (j + 1, i + 1)
    return (j, i), (j + 1, i + 1), (j + 1, i)


@inline
def _row_range(screen, a, b, c, height):
    """Rows [r0, r1) whose pixel centres the triangle can cover; empty when culled by the near plane."""
    if screen[a[0], a[1], 2] <= NEAR or screen[b[0], b[1], 2] <= NEAR or screen[c[0], c[1], 2] <= NEAR:
        return 0, 0
    ay, by, cy = screen[a[0], a[1], 1], screen[b[0], b[1], 1], screen[c[0], c[1], 1]
    r0 = max(0, int(math.ceil(min(ay, min(by, cy)) - 0.5)))
    r1 = min(height, int(math.floor(max(ay, max(by, cy)) - 0.5)) + 1)
    return r0, max(r0, r1)


@serial
def _grid_rows_cells(j0, j1, screen, height, rows, live, spans):
    ws = screen.shape[1]
    for j in range(j0, j1):
        lo, hi = height, 0
        for i in range(ws - 1):
            cell = j * (ws - 1) + i
            c0, c1, bits = height, 0, np.uint8(0)
            for t in range(2):
                a, b, c = _triangle(j, i, t)
                r0, r1 = _row_range(screen, a, b, c, height)
                if r1 > r0:
                    c0, c1, bits = min(c0, r0), max(c1, r1), bits | np.uint8(1 << t)
            rows[cell, 0], rows[cell, 1], live[cell] = c0, max(c0, c1), bits
            if bits:
                lo, hi = min(lo, c0), max(hi, c1)
        spans[j, 0], spans[j, 1] = lo, hi


@kernel
def _cell_rows(screen, height, rows, live, spans):
    cells = screen.shape[0] - 1
    for b in nb.prange((cells + ROWS - 1) // ROWS):
        _grid_rows_cells(b * ROWS, min(cells, (b + 1) * ROWS), screen, height, rows, live, spans)


@inline
def _inverse_area(ax, ay, bx, by, cx, cy, on):
    """1 over a triangle's doubled signed area, 0 where it is not rasterised: culled (on false) or without area."""
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    return 1.0 / area if on and abs(area) >= 1e-12 else 0.0


@inline
def _weights(ax, ay, bx, by, cx, cy, sx, sy, inv_area):
    """A triangle's barycentric weights of vertices a and b at (sx, sy); where it is not rasterised (inv_area 0),
    weights that no pixel takes."""
    if inv_area == 0.0:
        return -1.0, -1.0
    wa = ((bx - sx) * (cy - sy) - (by - sy) * (cx - sx)) * inv_area
    wb = ((cx - sx) * (ay - sy) - (cy - sy) * (ax - sx)) * inv_area
    return wa, wb


@serial
def _raster_band(y0, vertices, cells, image):
    """Rasterise into rows [y0, y0 + band_rows) the cells that can cover them, in the mesh's order, with a 1/z
    depth test (the first of equal depths stays). A cell's two triangles share its bounding box, which holds each of
    their pixels about once where a box per triangle holds them twice: they are drawn in one pass over it, each pixel
    from the first that covers its centre, or, where the cell folds over itself, one after the other. (One flat
    loop: per-cell helpers taking the arrays would cost numba reference counting per call.)"""
    screen, attr, rows, lives, spans = vertices.screen, vertices.attr, cells.rows, cells.live, cells.spans
    out_prev, out_zinv = image.prev, image.zinv
    ws = screen.shape[1]
    y1, width = min(out_zinv.shape[0], y0 + cells.band_rows), out_zinv.shape[1]
    out_zinv[y0:y1] = 0.0
    for j in range(spans.shape[0]):
        if spans[j, 0] >= y1 or spans[j, 1] <= y0:
            continue
        for i in range(ws - 1):
            cell = j * (ws - 1) + i
            ry0, ry1, live = max(y0, rows[cell, 0]), min(y1, rows[cell, 1]), lives[cell]
            if ry0 >= ry1:
                continue
            # triangle 0 is (p, q, r), triangle 1 (p, r, s) (_triangle); a culled one's own vertex leaves the box
            px, py, qx, qy = screen[j, i, 0], screen[j, i, 1], screen[j, i + 1, 0], screen[j, i + 1, 1]
            rx, ry, sx, sy = screen[j + 1, i + 1, 0], screen[j + 1, i + 1, 1], screen[j + 1, i, 0], screen[j + 1, i, 1]
            on0, on1 = (live & 1) != 0, (live & 2) != 0
            xmin = min(px, rx, qx if on0 else px, sx if on1 else px)
            xmax = max(px, rx, qx if on0 else px, sx if on1 else px)
            rx0, rx1 = max(0, int(math.ceil(xmin - 0.5))), min(width, int(math.floor(xmax - 0.5)) + 1)
            if rx0 >= rx1:
                continue
            # per-vertex attributes, already over z (_mesh_vertices), so each pixel only blends them
            vp = (attr[j, i, 0], attr[j, i, 1], attr[j, i, 2], attr[j, i, 3])
            vq = (attr[j, i + 1, 0], attr[j, i + 1, 1], attr[j, i + 1, 2], attr[j, i + 1, 3])
            vr = (attr[j + 1, i + 1, 0], attr[j + 1, i + 1, 1], attr[j + 1, i + 1, 2], attr[j + 1, i + 1, 3])
            vs = (attr[j + 1, i, 0], attr[j + 1, i, 1], attr[j + 1, i, 2], attr[j + 1, i, 3])
            inv0, inv1 = _inverse_area(px, py, qx, qy, rx, ry, on0), _inverse_area(px, py, rx, ry, sx, sy, on1)
            # a cell whose triangles turn opposite ways folds over itself (a depth edge seen from aside): there they
            # overlap, and each is drawn in a pass of its own, so that the depth test decides between them
            folded = inv0 * inv1 < 0.0
            for k in range(2 if folded else 1):
                i0, i1 = (inv0 if k == 0 else 0.0, inv1 if k == 1 else 0.0) if folded else (inv0, inv1)
                da0, db0, da1, db1 = (qy - ry) * i0, (ry - py) * i0, (ry - sy) * i1, (sy - py) * i1
                # barycentric weights are affine in the pixel position: stepped along x. On a still view the grid's
                # vertices and edges pass through pixel centres: EDGE keeps the rounding of these sums from leaving
                # such a centre out of both triangles
                for y in range(ry0, ry1):
                    cy, cx = y + 0.5, rx0 + 0.5
                    wa0, wb0 = _weights(px, py, qx, qy, rx, ry, cx, cy, i0)
                    wa1, wb1 = _weights(px, py, rx, ry, sx, sy, cx, cy, i1)
                    for x in range(rx0, rx1):
                        wc0, wc1 = 1.0 - wa0 - wb0, 1.0 - wa1 - wb1
                        in0 = wa0 >= -EDGE and wb0 >= -EDGE and wc0 >= -EDGE
                        if in0 or (wa1 >= -EDGE and wb1 >= -EDGE and wc1 >= -EDGE):
                            # the first that covers the centre: triangle 0 with weights (wp, wq, wr), or 1 (wp, wr, ws)
                            wp, wq, wr, ws_ = (wa0, wb0, wc0, 0.0) if in0 else (wa1, 0.0, wb1, wc1)
                            iz = wp * vp[3] + wq * vq[3] + wr * vr[3] + ws_ * vs[3]
                            if iz > out_zinv[y, x]:
                                out_zinv[y, x] = iz
                                # over the triangle's own three vertices, in a branch each: a fourth term, a zero
                                # product, would add no bit, and selects cost more than the branch
                                if in0:
                                    zp = wa0 * vp[2] + wb0 * vq[2] + wc0 * vr[2]
                                    u = (wa0 * vp[0] + wb0 * vq[0] + wc0 * vr[0]) / zp
                                    v = (wa0 * vp[1] + wb0 * vq[1] + wc0 * vr[1]) / zp
                                else:
                                    zp = wa1 * vp[2] + wb1 * vr[2] + wc1 * vs[2]
                                    u = (wa1 * vp[0] + wb1 * vr[0] + wc1 * vs[0]) / zp
                                    v = (wa1 * vp[1] + wb1 * vr[1] + wc1 * vs[1]) / zp
                                out_prev[0, y, x], out_prev[1, y, x] = u, v
                        wa0 += da0
                        wb0 += db0
                        wa1 += da1
                        wb1 += db1


@kernel
def _raster_mesh(vertices, cells, image, counter, threads):
    bands = (image.zinv.shape[0] + cells.band_rows - 1) // cells.band_rows
    for _ in nb.prange(threads):
        band = claim(counter)
        while band < bands:
            _raster_band(band * cells.band_rows, vertices, cells, image)
            band = claim(counter)


@serial
def _same(a, b):
    """Whether two arrays of one size hold the same elements, read flat, without the temporary mask
    np.array_equal allocates (given their bits as integers, the same bits)."""
    a, b = a.reshape(-1), b.reshape(-1)
    for i in range(a.shape[0]):
        if a[i] != b[i]:
            return False
    return True


@serial
def _onto_itself(image):
    """Whether every covered pixel of a rasterised mesh reprojects exactly onto its own centre (a still view:
    the support pixels' centres are the vertices), read until the first that does not."""
    prev, zinv = image.prev, image.zinv
    h, w = zinv.shape
    for y in range(h):
        for x in range(w):
            if zinv[y, x] > 0.0 and (prev[0, y, x] != x + 0.5 or prev[1, y, x] != y + 0.5):
                return False
    return True


class SupportGrid(NamedTuple):
    """What a GridProjection projects: the support grid's pixel centres in the previous full-resolution image, their
    hit distances (hs, ws), and the previous and current cameras."""

    previous: EyeCamera
    grid_x: np.ndarray
    grid_y: np.ndarray
    depth: np.ndarray
    current: EyeCamera


class GridProjection:
    """The support grid of weier2016 section 3.2 (pixel centres grid_x, grid_y of the previous full-resolution image,
    hit distances depth (hs, ws)) unprojected with the previous camera and projected into the current one, once per
    change of those inputs, at every image size a coarse mesh of it rasterises: the meshes of one grid at several
    sizes (weier16's at full and at support resolution) share it, the sizes given at the start or met as they come.
    `version` counts the projections."""

    def __init__(self, sizes: tuple[tuple[int, int], ...] = ()):
        self.sizes: list[tuple[int, int]] = list(sizes)  # (width, height) of each image the meshes rasterise
        self._screens = np.empty((0, 0, 0, 3))  # (sizes, hs, ws, 3)
        self._attr = np.empty((0, 0, VERTEX_ATTRS))
        self._inputs: tuple[np.ndarray, ...] = ()  # the last projection's inputs, copied (_unchanged)
        self.version = 0

    def _unchanged(self, inputs: tuple[np.ndarray, ...]) -> bool:
        """Whether these inputs are the last call's, bit for bit; remembers them for the next call."""
        shapes = [(a.shape, a.dtype) for a in inputs]
        if shapes != [(a.shape, a.dtype) for a in self._inputs]:
            self._inputs = tuple(a.copy() for a in inputs)
            return False
        same = all(_same(a.view(np.uint32), b.view(np.uint32)) for a, b in zip(inputs, self._inputs, strict=True))
        for a, b in zip(inputs, self._inputs, strict=True):
            np.copyto(b, a)
        return same

    def project(self, grid: SupportGrid, size: tuple[int, int]) -> MeshVertices:
        """The vertices, with pixel coordinates at `size` (width, height): projected anew where the grid's inputs
        changed since the last call, or where `size` is new."""
        previous, grid_x, grid_y, depth, current = grid
        hs, ws = depth.shape
        if size not in self.sizes:
            self.sizes.append(size)
            self._inputs = ()
        if self._screens.shape[:3] != (len(self.sizes), hs, ws):
            self._screens = np.empty((len(self.sizes), hs, ws, 3))
            self._attr = np.empty((hs, ws, VERTEX_ATTRS))
        prev, cur = camera_arrays(previous), camera_arrays(current)
        if not self._unchanged((*prev, *cur, grid_x, grid_y, depth)):
            frustums = np.stack([camera_arrays(current, w, h).frustum for w, h in self.sizes])
            _mesh_vertices(prev, grid_x, grid_y, depth, cur, frustums, self._screens, self._attr)
            self.version += 1
        return MeshVertices(self._screens[self.sizes.index(size)], self._attr)


class CoarseMesh:
    """weier2016 section 3.2's coarse-mesh reprojection: a GridProjection's vertices rasterised at width x height
    with a 1/z depth test.

    Its buffers persist across frames and are replaced only when the grid or the image changes size. The image
    depends on nothing but the projection's inputs, so a call with the same inputs as the last one, bit for bit (a
    still view: the same cameras and support depth), returns the image it left, rasterised once. `still`: whether
    the image reprojects every covered pixel onto its own centre (_onto_itself). distances() measures the
    image's pixels once per rasterisation. Meshes of one grid at other sizes share its `projection`.
    """

    def __init__(self, projection: GridProjection | None = None):
        self.projection = projection or GridProjection()
        self.image = MeshImage(np.empty((2, 0, 0), np.float32), np.empty((0, 0), np.float32))
        self._cells = CellRows(np.empty((0, 2), np.int64), np.empty(0, np.uint8), np.empty((0, 2), np.int64), 1)
        self._version = -1  # the projection's version the image was rasterised from
        self.still = False
        self._current: CameraArrays | None = None  # the current camera, of the image
        self._distance = np.empty((0, 0), np.float32)
        self._measured = False  # whether _distance holds the image's distances

    def reproject(
        self,
        previous: EyeCamera,
        grid_x: np.ndarray,
        grid_y: np.ndarray,
        depth: np.ndarray,
        current: EyeCamera,
        width: int,
        height: int,
    ) -> MeshImage:
        """The mesh rasterised at width x height (a view of buffers that the next call overwrites)."""
        hs, ws = depth.shape
        rows = max(hs - 1, 0)
        cells = rows * max(ws - 1, 0)
        if self._cells.live.shape[0] != cells or self._cells.spans.shape[0] != rows:
            self._cells = CellRows(
                np.empty((cells, 2), np.int64), np.empty(cells, np.uint8), np.empty((rows, 2), np.int64), 1
            )
        if self.image.zinv.shape != (height, width):
            self.image = MeshImage(np.empty((2, height, width), np.float32), np.empty((height, width), np.float32))
            self._version = -1
        vertices = self.projection.project(SupportGrid(previous, grid_x, grid_y, depth, current), (width, height))
        if self.projection.version == self._version:
            return self.image
        cells = self._cells._replace(band_rows=max(1, height // BANDS))
        _cell_rows(vertices.screen, height, cells.rows, cells.live, cells.spans)
        dynamic(_raster_mesh, vertices, cells, self.image)
        self.still = _onto_itself(self.image)
        self._version = self.projection.version
        self._current, self._measured = camera_arrays(current, width, height), False
        return self.image

    def distances(self) -> np.ndarray:
        """Each pixel's distance from the current eye at the depth the image gives it (view_distance at 1 / zinv;
        inf where the mesh does not cover it), in float32; measured once per rasterisation, so that a still view
        reads what the cache's surface test would compute pixel by pixel."""
        if not self._measured:
            if self._distance.shape != self.image.zinv.shape:
                self._distance = np.empty(self.image.zinv.shape, np.float32)
            _distances(self._current, self.image.zinv, self._distance)
            self._measured = True
        return self._distance


@kernel
def _distances(cam, zinv, out):
    """CoarseMesh.distances, a row per task; the row's divisions and roots vectorise."""
    h, w = zinv.shape
    for y in nb.prange(h):
        for x in range(w):
            out[y, x] = np.float32(view_distance(cam, x + 0.5, y + 0.5, np.divide(1.0, zinv[y, x])))


@serial
def _step(qx, qy, sx, sy, covered):
    """How far a neighbour at (sx, sy) in the previous image lies from (qx, qy) along either axis, if covered."""
    return max(abs(sx - qx), abs(sy - qy)) if covered else np.float32(0.0)


@inline
def row_footprints(prev, covered, mask, y, out):
    """weier2016 section 3.2's pixel footprint along row y: how far one pixel step moves in the previous image,
    the largest step to a 4-neighbour that is covered (covered & mask nonzero) along either axis, 0 without
    one. The row's interior is written out without branches or array-taking helpers, so that numba
    vectorises it (prev in planes); the two end pixels clamp their neighbours."""
    px, py = prev[0], prev[1]
    h, w = covered.shape
    up, down = max(y - 1, 0), min(y + 1, h - 1)
    mu, md = mask if y > 0 else 0, mask if y + 1 < h else 0
    zero = np.float32(0.0)
    for x in range(1, w - 1):
        qx, qy = px[y, x], py[y, x]
        left = max(abs(px[y, x - 1] - qx), abs(py[y, x - 1] - qy)) if covered[y, x - 1] & mask else zero
        right = max(abs(px[y, x + 1] - qx), abs(py[y, x + 1] - qy)) if covered[y, x + 1] & mask else zero
        above = max(abs(px[up, x] - qx), abs(py[up, x] - qy)) if covered[up, x] & mu else zero
        below = max(abs(px[down, x] - qx), abs(py[down, x] - qy)) if covered[down, x] & md else zero
        out[x] = max(max(left, right), max(above, below))
    for x in (0, w - 1):
        qx, qy = px[y, x], py[y, x]
        lx, rx = max(x - 1, 0), min(x + 1, w - 1)
        ml, mr = mask if x > 0 else 0, mask if x + 1 < w else 0
        across = max(
            _step(qx, qy, px[y, lx], py[y, lx], covered[y, lx] & ml),
            _step(qx, qy, px[y, rx], py[y, rx], covered[y, rx] & mr),
        )
        along = max(
            _step(qx, qy, px[up, x], py[up, x], covered[up, x] & mu),
            _step(qx, qy, px[down, x], py[down, x], covered[down, x] & md),
        )
        out[x] = max(across, along)


@serial
def gaussian_taps(color, qx, qy, sigma, samples, key):
    """The mean of `samples` bilinear taps of color around (qx, qy), normally distributed with deviation
    sigma (weier2016 section 3.2: a footprint wider than a pixel, sampled at random)."""
    r = g = b = 0.0
    for k in range(samples):
        u1 = max(uniform(key, 7, 2 * k), 1e-12)
        u2 = uniform(key, 7, 2 * k + 1)
        rad = sigma * math.sqrt(-2.0 * math.log(u1))
        sr, sg, sb = bilinear3(color, qx + rad * math.cos(2 * math.pi * u2), qy + rad * math.sin(2 * math.pi * u2))
        r, g, b = r + sr / samples, g + sg / samples, b + sb / samples
    return r, g, b


@serial
def nearest_texel(x, y, w, h):
    """Row and column of the pixel containing continuous (x, y), clamped to the image (x, y not NaN)."""
    return min(max(int(y), 0), h - 1), min(max(int(x), 0), w - 1)
