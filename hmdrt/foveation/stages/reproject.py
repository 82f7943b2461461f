"""Moving information between frames: back-projection of surface points into an earlier eye camera,
and image lookups at the continuous pixel coordinates it yields.

World points come from a pixel's view ray and hit distance; a miss (infinite depth) is a point at
infinity, so the sky reprojects by rotation alone. Used by kim2021 (sections 4.4, 4.7), weier2016
(section 3.2) and weier2018 (section 3.1, TAA).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.optics.camera import EyeCamera
from hmdrt.rng import uniform

FAR = 1e7  # metres: where a miss is placed so that it reprojects as a direction


class CameraArrays(NamedTuple):
    """An EyeCamera as plain numbers for the kernels."""

    position: np.ndarray  # (3,) float64
    rotation: np.ndarray  # (3, 3) float64, world-from-eye
    frustum: np.ndarray  # (6,) tan_left, tan_right, tan_up, tan_down, width, height


def camera_arrays(camera: EyeCamera) -> CameraArrays:
    frustum = np.array([camera.tan_left, camera.tan_right, camera.tan_up, camera.tan_down, camera.width, camera.height])
    return CameraArrays(np.asarray(camera.position, np.float64), np.asarray(camera.rotation, np.float64), frustum)


@nb.njit(cache=True, nogil=True, inline="always")
def ray_direction(cam, x, y):
    """World unit direction of the view ray through continuous pixel (x, y)."""
    f = cam.frustum
    tx = f[0] + x * (f[1] - f[0]) / f[4]
    ty = f[2] - y * (f[2] - f[3]) / f[5]
    inv = 1.0 / math.sqrt(tx * tx + ty * ty + 1.0)
    r = cam.rotation
    ex, ey, ez = tx * inv, ty * inv, -inv
    return (
        r[0, 0] * ex + r[0, 1] * ey + r[0, 2] * ez,
        r[1, 0] * ex + r[1, 1] * ey + r[1, 2] * ez,
        r[2, 0] * ex + r[2, 1] * ey + r[2, 2] * ez,
    )


@nb.njit(cache=True, nogil=True, inline="always")
def project(cam, px, py, pz):
    """Continuous pixel coordinates and distance from the camera of world point p; x is NaN behind it."""
    dx, dy, dz = px - cam.position[0], py - cam.position[1], pz - cam.position[2]
    r = cam.rotation
    lx = r[0, 0] * dx + r[1, 0] * dy + r[2, 0] * dz
    ly = r[0, 1] * dx + r[1, 1] * dy + r[2, 1] * dz
    lz = r[0, 2] * dx + r[1, 2] * dy + r[2, 2] * dz
    dist = math.sqrt(dx * dx + dy * dy + dz * dz)
    if lz >= 0.0:
        return math.nan, math.nan, dist
    f = cam.frustum
    x = (lx / -lz - f[0]) / (f[1] - f[0]) * f[4]
    y = (f[2] - ly / -lz) / (f[2] - f[3]) * f[5]
    return x, y, dist


@nb.njit(cache=True, nogil=True, inline="always")
def world_point(cam, x, y, depth):
    """The point at hit distance `depth` along the view ray of pixel (x, y); FAR for a miss."""
    dx, dy, dz = ray_direction(cam, x, y)
    d = depth if depth < FAR else FAR
    return cam.position[0] + d * dx, cam.position[1] + d * dy, cam.position[2] + d * dz


@nb.njit(parallel=True, cache=True, nogil=True)
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


@nb.njit(cache=True, nogil=True, inline="always")
def nearest_index(x, y, w, h):
    """Row-major index of the pixel containing continuous (x, y), or -1 outside the image or NaN."""
    if not (x >= 0.0 and y >= 0.0 and x < w and y < h):
        return -1
    return int(y) * w + int(x)


@nb.njit(cache=True, nogil=True, inline="always")
def bilinear3(image, x, y):
    """The three channels of image (h, w, 3) at continuous (x, y), clamped at the border."""
    h, w = image.shape[0], image.shape[1]
    fx, fy = x - 0.5, y - 0.5
    x0, y0 = math.floor(fx), math.floor(fy)
    ax, ay = fx - x0, fy - y0
    ix0, iy0 = min(max(int(x0), 0), w - 1), min(max(int(y0), 0), h - 1)
    ix1, iy1 = min(max(int(x0) + 1, 0), w - 1), min(max(int(y0) + 1, 0), h - 1)
    w00, w01, w10, w11 = (1.0 - ax) * (1.0 - ay), ax * (1.0 - ay), (1.0 - ax) * ay, ax * ay
    return (
        w00 * image[iy0, ix0, 0] + w01 * image[iy0, ix1, 0] + w10 * image[iy1, ix0, 0] + w11 * image[iy1, ix1, 0],
        w00 * image[iy0, ix0, 1] + w01 * image[iy0, ix1, 1] + w10 * image[iy1, ix0, 1] + w11 * image[iy1, ix1, 1],
        w00 * image[iy0, ix0, 2] + w01 * image[iy0, ix1, 2] + w10 * image[iy1, ix0, 2] + w11 * image[iy1, ix1, 2],
    )


# -- weier2016 section 3.2: reprojection through a coarse mesh built from the support G-buffer --

NEAR = 1e-4  # metres: mesh vertices closer to (or behind) the current eye drop their triangles
NEIGHBOUR_DX, NEIGHBOUR_DY = (-1, 1, 0, 0), (0, 0, -1, 1)
MESH_ATTRS = 5  # out: previous pixel x, y and world x, y, z
VERTEX_ATTRS = 6  # in: previous pixel x z, y z and z (z: previous view depth), world x, y, z: all linear
# in the world on a planar facet, so perspective-correct interpolation recovers x and y exactly


@nb.njit(cache=True, nogil=True, inline="always")
def project_view(cam, px, py, pz):
    """Continuous pixel coordinates and view depth (along -Z, positive in front) of world point p."""
    dx, dy, dz = px - cam.position[0], py - cam.position[1], pz - cam.position[2]
    r = cam.rotation
    lx = r[0, 0] * dx + r[1, 0] * dy + r[2, 0] * dz
    ly = r[0, 1] * dx + r[1, 1] * dy + r[2, 1] * dz
    z = -(r[0, 2] * dx + r[1, 2] * dy + r[2, 2] * dz)
    if z <= NEAR:
        return 0.0, 0.0, z
    f = cam.frustum
    return (lx / z - f[0]) / (f[1] - f[0]) * f[4], (f[2] - ly / z) / (f[2] - f[3]) * f[5], z


@nb.njit(parallel=True, cache=True, nogil=True)
def _mesh_vertices(prev, grid_x, grid_y, depth, cur, screen, attr):
    hs, ws = depth.shape
    for j in nb.prange(hs):
        for i in range(ws):
            px, py, pz = world_point(prev, grid_x[i], grid_y[j], depth[j, i])
            screen[j, i, 0], screen[j, i, 1], screen[j, i, 2] = project_view(cur, px, py, pz)
            zp = project_view(prev, px, py, pz)[2]
            attr[j, i, 0], attr[j, i, 1], attr[j, i, 2] = grid_x[i] * zp, grid_y[j] * zp, zp
            attr[j, i, 3], attr[j, i, 4], attr[j, i, 5] = px, py, pz


@nb.njit(cache=True, nogil=True, inline="always")
def _triangle(j, i, t):
    """Grid vertices (row, column) of triangle t (0 or 1) of grid cell (j, i)."""
    if t == 0:
        return (j, i), (j, i + 1), (j + 1, i + 1)
    return (j, i), (j + 1, i + 1), (j + 1, i)


@nb.njit(cache=True, nogil=True, inline="always")
def _row_range(screen, a, b, c, height):
    """Rows [r0, r1) whose pixel centres the triangle can cover; empty when culled by the near plane."""
    if screen[a[0], a[1], 2] <= NEAR or screen[b[0], b[1], 2] <= NEAR or screen[c[0], c[1], 2] <= NEAR:
        return 0, 0
    ay, by, cy = screen[a[0], a[1], 1], screen[b[0], b[1], 1], screen[c[0], c[1], 1]
    r0 = max(0, int(math.ceil(min(ay, min(by, cy)) - 0.5)))
    r1 = min(height, int(math.floor(max(ay, max(by, cy)) - 0.5)) + 1)
    return r0, max(r0, r1)


@nb.njit(cache=True, nogil=True, inline="always")
def _raster_triangle(screen, attr, a, b, c, y0, y1, width, out_attr, out_zinv):
    """Rasterise triangle (a, b, c) of grid vertices into rows [y0, y1) with a 1/z depth test."""
    ax, ay, az = screen[a[0], a[1], 0], screen[a[0], a[1], 1], screen[a[0], a[1], 2]
    bx, by, bz = screen[b[0], b[1], 0], screen[b[0], b[1], 1], screen[b[0], b[1], 2]
    cx, cy, cz = screen[c[0], c[1], 0], screen[c[0], c[1], 1], screen[c[0], c[1], 2]
    ymin, ymax = min(ay, min(by, cy)), max(ay, max(by, cy))
    ry0, ry1 = max(y0, int(math.ceil(ymin - 0.5))), min(y1, int(math.floor(ymax - 0.5)) + 1)
    xmin, xmax = min(ax, min(bx, cx)), max(ax, max(bx, cx))
    rx0, rx1 = max(0, int(math.ceil(xmin - 0.5))), min(width, int(math.floor(xmax - 0.5)) + 1)
    area = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
    if ry0 >= ry1 or rx0 >= rx1 or abs(area) < 1e-12:
        return
    inv_area = 1.0 / area
    iza, izb, izc = 1.0 / az, 1.0 / bz, 1.0 / cz
    # per-vertex attributes times 1/z, so each pixel only blends them
    a0, a1, a2 = attr[a[0], a[1], 0] * iza, attr[a[0], a[1], 1] * iza, attr[a[0], a[1], 2] * iza
    a3, a4, a5 = attr[a[0], a[1], 3] * iza, attr[a[0], a[1], 4] * iza, attr[a[0], a[1], 5] * iza
    b0, b1, b2 = attr[b[0], b[1], 0] * izb, attr[b[0], b[1], 1] * izb, attr[b[0], b[1], 2] * izb
    b3, b4, b5 = attr[b[0], b[1], 3] * izb, attr[b[0], b[1], 4] * izb, attr[b[0], b[1], 5] * izb
    c0, c1, c2 = attr[c[0], c[1], 0] * izc, attr[c[0], c[1], 1] * izc, attr[c[0], c[1], 2] * izc
    c3, c4, c5 = attr[c[0], c[1], 3] * izc, attr[c[0], c[1], 4] * izc, attr[c[0], c[1], 5] * izc
    # barycentric weights are affine in the pixel position: step them along x
    dwa_dx, dwb_dx = (by - cy) * inv_area, (cy - ay) * inv_area
    for y in range(ry0, ry1):
        sy = y + 0.5
        sx = rx0 + 0.5
        wa = ((bx - sx) * (cy - sy) - (by - sy) * (cx - sx)) * inv_area
        wb = ((cx - sx) * (ay - sy) - (cy - sy) * (ax - sx)) * inv_area
        for x in range(rx0, rx1):
            wc = 1.0 - wa - wb
            if wa >= 0.0 and wb >= 0.0 and wc >= 0.0:
                iz = wa * iza + wb * izb + wc * izc
                if iz > out_zinv[y, x]:
                    out_zinv[y, x] = iz
                    zp = wa * a2 + wb * b2 + wc * c2
                    out_attr[y, x, 0] = (wa * a0 + wb * b0 + wc * c0) / zp
                    out_attr[y, x, 1] = (wa * a1 + wb * b1 + wc * c1) / zp
                    out_attr[y, x, 2] = (wa * a3 + wb * b3 + wc * c3) / iz
                    out_attr[y, x, 3] = (wa * a4 + wb * b4 + wc * c4) / iz
                    out_attr[y, x, 4] = (wa * a5 + wb * b5 + wc * c5) / iz
            wa += dwa_dx
            wb += dwb_dx


@nb.njit(cache=True, nogil=True)
def _triangle_rows(screen, height, rows):
    hs, ws = screen.shape[0], screen.shape[1]
    for j in range(hs - 1):
        for i in range(ws - 1):
            for t in range(2):
                a, b, c = _triangle(j, i, t)
                rows[(j * (ws - 1) + i) * 2 + t] = _row_range(screen, a, b, c, height)


@nb.njit(cache=True, nogil=True)
def _bin_triangles(rows, band_rows, bands):
    """Triangle indices per band of rows (a counting sort): start offsets (bands + 1) and the list."""
    counts = np.zeros(bands + 1, np.int64)
    for t in range(rows.shape[0]):
        r0, r1 = rows[t, 0], rows[t, 1]
        if r1 > r0:
            for band in range(r0 // band_rows, (r1 - 1) // band_rows + 1):
                counts[band + 1] += 1
    starts = np.cumsum(counts)
    fill = starts[:-1].copy()
    members = np.empty(starts[-1], np.int64)
    for t in range(rows.shape[0]):
        r0, r1 = rows[t, 0], rows[t, 1]
        if r1 > r0:
            for band in range(r0 // band_rows, (r1 - 1) // band_rows + 1):
                members[fill[band]] = t
                fill[band] += 1
    return starts, members


@nb.njit(parallel=True, cache=True, nogil=True)
def _raster_mesh(screen, attr, width, height, band_rows, starts, members, out_attr, out_zinv):
    ws = screen.shape[1]
    for band in nb.prange(starts.shape[0] - 1):
        y0, y1 = band * band_rows, min(height, (band + 1) * band_rows)
        for y in range(y0, y1):
            for x in range(width):
                out_zinv[y, x] = 0.0
        for k in range(starts[band], starts[band + 1]):
            t = members[k]
            cell = t // 2
            a, b, c = _triangle(cell // (ws - 1), cell % (ws - 1), t % 2)
            _raster_triangle(screen, attr, a, b, c, y0, y1, width, out_attr, out_zinv)


def reproject_mesh(
    previous: EyeCamera,
    grid_x: np.ndarray,
    grid_y: np.ndarray,
    depth: np.ndarray,
    current: EyeCamera,
    width: int,
    height: int,
) -> tuple[np.ndarray, np.ndarray]:
    """weier2016's coarse-mesh reprojection: the support grid (pixel centres grid_x, grid_y of the
    previous full-resolution image, hit distances depth (hs, ws)) is unprojected with the previous
    camera, projected with the current one and rasterised at width x height.

    Returns per pixel the interpolated previous-frame pixel coordinates and world point (h, w, 5) and
    1/z of the nearest surface (h, w), 0 where the mesh does not cover the pixel.
    """
    prev, cur = camera_arrays(previous), camera_arrays(current)
    cur = CameraArrays(cur.position, cur.rotation, np.array([*cur.frustum[:4], width, height]))
    hs, ws = depth.shape
    screen = np.empty((hs, ws, 3))
    attr = np.empty((hs, ws, VERTEX_ATTRS))
    _mesh_vertices(
        prev, grid_x.astype(np.float64), grid_y.astype(np.float64), depth.astype(np.float64), cur, screen, attr
    )
    rows = np.empty((2 * (hs - 1) * (ws - 1), 2), np.int64)
    _triangle_rows(screen, height, rows)
    band_rows = max(1, height // 64)
    bands = (height + band_rows - 1) // band_rows
    starts, members = _bin_triangles(rows, band_rows, bands)
    out_attr = np.empty((height, width, MESH_ATTRS), np.float32)
    out_zinv = np.empty((height, width), np.float32)
    _raster_mesh(screen, attr, width, height, band_rows, starts, members, out_attr, out_zinv)
    return out_attr, out_zinv


@nb.njit(parallel=True, cache=True, nogil=True)
def _gather(mesh, zinv, cur, color, state, samples, seed, out_color, out_state, out_dist):
    h, w = zinv.shape
    ph, pw = color.shape[0], color.shape[1]
    for y in nb.prange(h):
        for x in range(w):
            if zinv[y, x] <= 0.0:
                out_dist[y, x] = math.nan
                continue
            qx, qy = mesh[y, x, 0], mesh[y, x, 1]
            # footprint: how far one pixel step moves in the previous image, from covered neighbours only
            footprint = 0.0
            for k in range(4):
                ny, nx = y + NEIGHBOUR_DY[k], x + NEIGHBOUR_DX[k]
                if 0 <= ny < h and 0 <= nx < w and zinv[ny, nx] > 0.0:
                    footprint = max(footprint, abs(mesh[ny, nx, 0] - qx), abs(mesh[ny, nx, 1] - qy))
            if footprint <= 1.5 or samples <= 1:
                r, g, b = bilinear3(color, qx, qy)
            else:
                # weier2016: random samples of the pixel footprint from a normal distribution
                sigma = 0.5 * footprint
                r = g = b = 0.0
                key = (y * w + x) * 64 + seed
                for k in range(samples):
                    u1 = max(uniform(key, 7, 2 * k), 1e-12)
                    u2 = uniform(key, 7, 2 * k + 1)
                    rad = sigma * math.sqrt(-2.0 * math.log(u1))
                    sr, sg, sb = bilinear3(
                        color, qx + rad * math.cos(2 * math.pi * u2), qy + rad * math.sin(2 * math.pi * u2)
                    )
                    r, g, b = r + sr / samples, g + sg / samples, b + sb / samples
            out_color[y, x, 0], out_color[y, x, 1], out_color[y, x, 2] = r, g, b
            j = nearest_index(qx, qy, pw, ph)
            if j < 0:
                j = min(max(int(qy), 0), ph - 1) * pw + min(max(int(qx), 0), pw - 1)
            for k in range(state.shape[2]):
                out_state[y, x, k] = state[j // pw, j % pw, k]
            ddx = mesh[y, x, 2] - cur.position[0]
            ddy = mesh[y, x, 3] - cur.position[1]
            ddz = mesh[y, x, 4] - cur.position[2]
            out_dist[y, x] = math.sqrt(ddx * ddx + ddy * ddy + ddz * ddz)


def gather_previous(
    mesh: np.ndarray,
    zinv: np.ndarray,
    current: EyeCamera,
    color: np.ndarray,
    state: np.ndarray,
    samples: int,
    seed: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The previous frame's colour and per-pixel state seen through the reprojected mesh.

    Colour is filtered over each pixel's footprint in the previous image (bilinear when the footprint
    is about a pixel, else the mean of `samples` normally distributed taps); state (cache info) takes
    the nearest texel, since ages and counts must not be blended. Also returns each covered pixel's
    distance from the current eye to the reprojected surface (NaN where uncovered).
    """
    h, w = zinv.shape
    out_color = np.zeros((h, w, 3), np.float32)
    out_state = np.zeros((h, w, state.shape[2]), np.float32)
    out_dist = np.empty((h, w), np.float32)
    _gather(mesh, zinv, camera_arrays(current), color, state, samples, seed, out_color, out_state, out_dist)
    return out_color, out_state, out_dist
