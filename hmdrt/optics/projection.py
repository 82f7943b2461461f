"""Camera projection for the kernels: an EyeCamera as plain arrays, view rays through continuous pixel
coordinates, world points at a hit distance or view depth, their projection into a camera, and lookups at
the continuous pixel coordinates that yields.

A miss (infinite depth) becomes a point at FAR, so that it reprojects as a direction. Continuous pixel
coordinates put pixel (i, j)'s centre at (i + 0.5, j + 0.5), as EyeCamera does.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from hmdrt.kernels.jit import inline, serial
from hmdrt.kernels.simd import rgb_bilinear
from hmdrt.optics.camera import EyeCamera

FAR = 1e7  # metres: where a miss is placed so that it reprojects as a direction


class CameraArrays(NamedTuple):
    """An EyeCamera as plain numbers for the kernels."""

    position: np.ndarray  # (3,) float64
    rotation: np.ndarray  # (3, 3) float64, world-from-eye
    frustum: np.ndarray  # (6,) tan_left, tan_right, tan_up, tan_down, width, height


def camera_arrays(camera: EyeCamera, width: int | None = None, height: int | None = None) -> CameraArrays:
    """The camera's arrays; width and height: its frustum over a pixel grid of that size instead of its own."""
    w, h = width or camera.width, height or camera.height
    frustum = np.array([camera.tan_left, camera.tan_right, camera.tan_up, camera.tan_down, w, h], np.float64)
    return CameraArrays(np.asarray(camera.position, np.float64), np.asarray(camera.rotation, np.float64), frustum)


@serial
def pixel_tangents(f, x, y):
    """The view ray's tangents (x right, y up) through continuous pixel (x, y) of frustum f. Divisions as ufuncs
    here and below: numba's zero-division branch on `/` keeps a loop that calls these from vectorising."""
    return f[0] + np.divide(x * (f[1] - f[0]), f[4]), f[2] - np.divide(y * (f[2] - f[3]), f[5])


@serial
def pixel_of(f, tx, ty):
    """Continuous pixel coordinates of the view ray with tangents (tx, ty) in frustum f."""
    return np.divide(tx - f[0], f[1] - f[0]) * f[4], np.divide(f[2] - ty, f[2] - f[3]) * f[5]


@inline
def to_eye(cam, px, py, pz):
    """World point p in the camera's eye frame (x right, y up, looking along -z)."""
    dx, dy, dz = px - cam.position[0], py - cam.position[1], pz - cam.position[2]
    r = cam.rotation
    return (
        r[0, 0] * dx + r[1, 0] * dy + r[2, 0] * dz,
        r[0, 1] * dx + r[1, 1] * dy + r[2, 1] * dz,
        r[0, 2] * dx + r[1, 2] * dy + r[2, 2] * dz,
    )


@inline
def ray_direction(cam, x, y):
    """World unit direction of the view ray through continuous pixel (x, y)."""
    tx, ty = pixel_tangents(cam.frustum, x, y)
    inv = np.divide(1.0, math.sqrt(tx * tx + ty * ty + 1.0))
    r = cam.rotation
    ex, ey, ez = tx * inv, ty * inv, -inv
    return (
        r[0, 0] * ex + r[0, 1] * ey + r[0, 2] * ez,
        r[1, 0] * ex + r[1, 1] * ey + r[1, 2] * ez,
        r[2, 0] * ex + r[2, 1] * ey + r[2, 2] * ez,
    )


@inline
def project(cam, px, py, pz):
    """Continuous pixel coordinates and distance from the camera of world point p; x is NaN behind it."""
    lx, ly, lz = to_eye(cam, px, py, pz)
    dist = math.sqrt(lx * lx + ly * ly + lz * lz)
    if lz >= 0.0:
        return math.nan, math.nan, dist
    x, y = pixel_of(cam.frustum, np.divide(lx, -lz), np.divide(ly, -lz))
    return x, y, dist


@inline
def world_point(cam, x, y, depth):
    """The point at hit distance `depth` along the view ray of pixel (x, y); FAR for a miss."""
    dx, dy, dz = ray_direction(cam, x, y)
    d = depth if depth < FAR else FAR
    return cam.position[0] + d * dx, cam.position[1] + d * dy, cam.position[2] + d * dz


@serial
def nearest_index(x, y, w, h):
    """Row-major index of the pixel containing continuous (x, y), or -1 outside the image or NaN."""
    if not (x >= 0.0 and y >= 0.0 and x < w and y < h):
        return -1
    return int(y) * w + int(x)


@serial
def bilinear3(image, x, y):
    """The three channels of image (h, w, 3), C-contiguous, at continuous (x, y), clamped at the border
    (bilinear_footprint, then blend_footprint)."""
    a, b, i, step_x, step_y = bilinear_footprint(x, y, image.shape[1], image.shape[0])
    return blend_footprint(image, i, step_x, step_y, a, b)  # indexed flat, without a reshaped view's reference count


@inline
def bilinear_footprint(x, y, w, h):
    """bilinear3's footprint at continuous (x, y) of an image (h, w, 3) read flat: the weights across and down
    (float64), the flat index of the top-left texel's first channel and the steps to its right and lower
    neighbours (uint64, 0 where the border clamps them). A row's footprints taken in one pass of selects
    vectorise; the gather (blend_footprint) then reads only texels."""
    fx, fy = x - 0.5, y - 0.5
    x0, y0 = np.floor(fx), np.floor(fy)
    ix, iy = min(max(int(x0), 0), w - 1), min(max(int(y0), 0), h - 1)
    step_x = np.uint64(3 * (min(max(int(x0) + 1, 0), w - 1) - ix))
    step_y = np.uint64(3 * w * (min(max(int(y0) + 1, 0), h - 1) - iy))
    return fx - x0, fy - y0, np.uint64(3 * (iy * w + ix)), step_x, step_y


@inline
def blend_footprint(flat, i, step_x, step_y, a, b):
    """The three channels at a bilinear_footprint (i, step_x, step_y, weights a, b) of an image read flat (any
    C-contiguous float32 array of its texels' channels), in float64:
    the weights (1 - a)(1 - b), a (1 - b), (1 - a) b and a b times the top-left, top-right, bottom-left and
    bottom-right texels, summed in that order (simd.rgb_bilinear: each texel one load, three channels at once)."""
    return rgb_bilinear(flat, i, step_x, step_y, a, b)


NEAR = 1e-4  # metres: mesh vertices closer to (or behind) the current eye drop their triangles


@inline
def view_point(cam, x, y, z):
    """The world point at view depth z (along -Z) on the view ray through continuous pixel (x, y)."""
    r = cam.rotation
    tx, ty = pixel_tangents(cam.frustum, x, y)
    return (
        cam.position[0] + z * (r[0, 0] * tx + r[0, 1] * ty - r[0, 2]),
        cam.position[1] + z * (r[1, 0] * tx + r[1, 1] * ty - r[1, 2]),
        cam.position[2] + z * (r[2, 0] * tx + r[2, 1] * ty - r[2, 2]),
    )


@inline
def view_distance(cam, x, y, z):
    """The distance from the eye of the point at view depth z on the view ray through pixel (x, y)."""
    tx, ty = pixel_tangents(cam.frustum, x, y)
    return z * math.sqrt(tx * tx + ty * ty + 1.0)


@inline
def project_view(cam, px, py, pz):
    """Continuous pixel coordinates and view depth (along -Z, positive in front) of world point p."""
    lx, ly, lz = to_eye(cam, px, py, pz)
    z = -lz
    if z <= NEAR:
        return 0.0, 0.0, z
    x, y = pixel_of(cam.frustum, np.divide(lx, z), np.divide(ly, z))
    return x, y, z
