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
    project,
    project_view,
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


class TriangleRows(NamedTuple):
    """The image rows each of the mesh's triangles can cover, and each row of grid cells: what a band of image
    rows needs to find its triangles, in the mesh's order, without sorting them."""

    rows: np.ndarray  # (triangles, 2) int64: the rows [r0, r1) a triangle can cover, empty when culled
    spans: np.ndarray  # (hs - 1, 2) int64: the rows [r0, r1) the triangles of a row of cells cover together
    band_rows: int


class MeshImage(NamedTuple):
    """The rasterised mesh per pixel: the previous frame's pixel coordinates of the surface seen there and
    its 1/z (current view depth), 0 where the mesh does not cover the pixel. The surface point itself lies
    on the pixel's view ray at depth 1/zinv (see view_point)."""

    prev: np.ndarray  # (2, h, w) float32: x and y planes
    zinv: np.ndarray  # (h, w) float32


@kernel
def _mesh_vertices(prev, grid_x, grid_y, depth, cur, vertices):
    screen, attr = vertices.screen, vertices.attr  # written through locals: see hmdrt/trace/blocks.py
    hs, ws = depth.shape
    for j in nb.prange(hs):
        for i in range(ws):
            px, py, pz = world_point(prev, grid_x[i], grid_y[j], depth[j, i])
            sx, sy, sz = project_view(cur, px, py, pz)
            screen[j, i, 0], screen[j, i, 1], screen[j, i, 2] = sx, sy, sz
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
def _grid_rows_triangles(j0, j1, screen, height, rows, spans):
    ws = screen.shape[1]
    for j in range(j0, j1):
        lo, hi = height, 0
        for i in range(ws - 1):
            for t in range(2):
                a, b, c = _triangle(j, i, t)
                r0, r1 = _row_range(screen, a, b, c, height)
                rows[(j * (ws - 1) + i) * 2 + t, 0] = r0
                rows[(j * (ws - 1) + i) * 2 + t, 1] = r1
                if r1 > r0:
                    lo, hi = min(lo, r0), max(hi, r1)
        spans[j, 0], spans[j, 1] = lo, hi


@kernel
def _triangle_rows(screen, height, rows, spans):
    cells = screen.shape[0] - 1
    for b in nb.prange((cells + ROWS - 1) // ROWS):
        _grid_rows_triangles(b * ROWS, min(cells, (b + 1) * ROWS), screen, height, rows, spans)


@serial
def _raster_band(y0, vertices, triangles, image):
    """Rasterise into rows [y0, y0 + band_rows) the triangles that can cover them, in the mesh's order, with a
    1/z depth test (the first of equal depths stays). (One flat loop: per-triangle helpers taking the arrays
    would cost numba reference counting per call.)"""
    screen, attr, rows, spans = vertices.screen, vertices.attr, triangles.rows, triangles.spans
    out_prev, out_zinv = image.prev, image.zinv
    ws = screen.shape[1]
    y1, width = min(out_zinv.shape[0], y0 + triangles.band_rows), out_zinv.shape[1]
    out_zinv[y0:y1] = 0.0
    for j in range(spans.shape[0]):
        if spans[j, 0] >= y1 or spans[j, 1] <= y0:
            continue
        for t in range(j * (ws - 1) * 2, (j + 1) * (ws - 1) * 2):
            if rows[t, 0] >= y1 or rows[t, 1] <= y0:
                continue
            cell = t // 2
            a, b, c = _triangle(j, cell % (ws - 1), t % 2)
            ax, ay = screen[a[0], a[1], 0], screen[a[0], a[1], 1]
            bx, by = screen[b[0], b[1], 0], screen[b[0], b[1], 1]
            cx, cy = screen[c[0], c[1], 0], screen[c[0], c[1], 1]
            ymin, ymax = min(ay, min(by, cy)), max(ay, max(by, cy))
            ry0, ry1 = max(y0, int(math.ceil(ymin - 0.5))), min(y1, int(math.floor(ymax - 0.5)) + 1)
            xmin, xmax = min(ax, min(bx, cx)), max(ax, max(bx, cx))
            rx0, rx1 = max(0, int(math.ceil(xmin - 0.5))), min(width, int(math.floor(xmax - 0.5)) + 1)
            area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
            if ry0 >= ry1 or rx0 >= rx1 or abs(area) < 1e-12:
                continue
            inv_area = 1.0 / area
            # per-vertex attributes, already over z (_mesh_vertices), so each pixel only blends them
            a0, a1, a2, iza = attr[a[0], a[1], 0], attr[a[0], a[1], 1], attr[a[0], a[1], 2], attr[a[0], a[1], 3]
            b0, b1, b2, izb = attr[b[0], b[1], 0], attr[b[0], b[1], 1], attr[b[0], b[1], 2], attr[b[0], b[1], 3]
            c0, c1, c2, izc = attr[c[0], c[1], 0], attr[c[0], c[1], 1], attr[c[0], c[1], 2], attr[c[0], c[1], 3]
            # barycentric weights are affine in the pixel position: stepped along x. On a still view the grid's
            # vertices and edges pass through pixel centres: EDGE keeps the rounding of these sums from leaving
            # such a centre out of both triangles, and the depth test keeps the first
            dwa_dx, dwb_dx = (by - cy) * inv_area, (cy - ay) * inv_area
            for y in range(ry0, ry1):
                sy, sx = y + 0.5, rx0 + 0.5
                wa = ((bx - sx) * (cy - sy) - (by - sy) * (cx - sx)) * inv_area
                wb = ((cx - sx) * (ay - sy) - (cy - sy) * (ax - sx)) * inv_area
                for x in range(rx0, rx1):
                    wc = 1.0 - wa - wb
                    if wa >= -EDGE and wb >= -EDGE and wc >= -EDGE:
                        iz = wa * iza + wb * izb + wc * izc
                        if iz > out_zinv[y, x]:
                            out_zinv[y, x] = iz
                            zp = wa * a2 + wb * b2 + wc * c2
                            out_prev[0, y, x] = (wa * a0 + wb * b0 + wc * c0) / zp
                            out_prev[1, y, x] = (wa * a1 + wb * b1 + wc * c1) / zp
                    wa += dwa_dx
                    wb += dwb_dx


@kernel
def _raster_mesh(vertices, triangles, image, counter, threads):
    bands = (image.zinv.shape[0] + triangles.band_rows - 1) // triangles.band_rows
    for _ in nb.prange(threads):
        band = claim(counter)
        while band < bands:
            _raster_band(band * triangles.band_rows, vertices, triangles, image)
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


class CoarseMesh:
    """weier2016 section 3.2's coarse-mesh reprojection: the support grid (pixel centres grid_x, grid_y of the
    previous full-resolution image, hit distances depth (hs, ws)) unprojected with the previous camera,
    projected with the current one and rasterised at width x height with a 1/z depth test.

    Its buffers persist across frames and are replaced only when the grid or the image changes size. The image
    depends on nothing but those inputs, so a call with the same inputs as the last one, bit for bit (a still
    view: the same cameras and support depth), returns the image it left, rasterised once. `still`: whether
    the image reprojects every covered pixel onto its own centre (_onto_itself). distances() measures the
    image's pixels once per rasterisation.
    """

    def __init__(self):
        self.image = MeshImage(np.empty((2, 0, 0), np.float32), np.empty((0, 0), np.float32))
        self._vertices = MeshVertices(np.empty((0, 0, 3)), np.empty((0, 0, VERTEX_ATTRS)))
        self._rows, self._spans = np.empty((0, 2), np.int64), np.empty((0, 2), np.int64)
        self._inputs: tuple[np.ndarray, ...] = ()  # the last call's inputs, copied (_unchanged)
        self.still = False
        self._current: CameraArrays | None = None  # the current camera, of the image
        self._distance = np.empty((0, 0), np.float32)
        self._measured = False  # whether _distance holds the image's distances

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
        if self._vertices.screen.shape[:2] != (hs, ws):
            self._vertices = MeshVertices(np.empty((hs, ws, 3)), np.empty((hs, ws, VERTEX_ATTRS)))
            cells = max(hs - 1, 0)
            self._rows = np.empty((2 * cells * max(ws - 1, 0), 2), np.int64)
            self._spans = np.empty((cells, 2), np.int64)
        if self.image.zinv.shape != (height, width):
            self.image = MeshImage(np.empty((2, height, width), np.float32), np.empty((height, width), np.float32))
            self._inputs = ()
        cur, prev = camera_arrays(current, width, height), camera_arrays(previous)
        if self._unchanged((*prev, *cur, grid_x, grid_y, depth)):
            return self.image
        _mesh_vertices(prev, grid_x, grid_y, depth, cur, self._vertices)
        _triangle_rows(self._vertices.screen, height, self._rows, self._spans)
        triangles = TriangleRows(self._rows, self._spans, max(1, height // BANDS))
        dynamic(_raster_mesh, self._vertices, triangles, self.image)
        self.still = _onto_itself(self.image)
        self._current, self._measured = cur, False
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
