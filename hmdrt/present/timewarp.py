"""Rotational timewarp: re-present the last good frame turned to the newest head orientation.

When a frame misses its VSync, VR compositors show the previous frame warped to the latest pose
instead of repeating it unchanged. This is orientation-only timewarp, the basic form that corrects
only the head's change in rotation and so is a 2D warp (Antonov, "Asynchronous Timewarp Examined",
Oculus developer blog, 2015; LaValle, "Virtual Reality", 2020, section 7.4): the scene is treated as
infinitely far, and each target pixel's view direction is looked up in the rendered image. Eye
positions are ignored: the frame carries no per-pixel depth here, which positional warps need, and
over one frame interval the head's turn, not its few millimetres of travel, is what moves distant
content by many pixels.

Target directions the rendered image does not cover take its nearest edge pixel (bilinear lookup
with clamped coordinates): LaValle (2020, section 7.4) advises repeating edge pixels rather than
turning them black. Directions behind the rendered eye (turns of tens of degrees) have no nearest
edge pixel and are black. Neither is silent: the result carries the fraction of pixels that fell
outside the rendered image.

Both cameras share their optics, so the map from a target pixel to the rendered image is a homography
(LaValle 2020, section 7.4): one 3x3 matrix per eye and frame, stepped along each row; the warp is one
gather kernel per eye into the caller's buffer.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.kernels.jit import kernel, serial
from hmdrt.optics.camera import EyeCamera

ROWS_PIXELS = 8192  # pixels per block of rows: each block allocates one row's lookups


class Timewarped(NamedTuple):
    """A warped frame and the fraction of its pixels whose direction the rendered frame did not cover."""

    image: np.ndarray  # (h, w, 3) float32
    outside: float  # in [0, 1]; 0 when every pixel was looked up inside the rendered image


class Warp(NamedTuple):
    """One eye's warp: the rendered image, the output and the homography between their pixels."""

    image: np.ndarray  # (h, w, 3) float32, as rendered
    out: np.ndarray  # (h, w, 3) float32, as seen from the target camera
    # (3, 3) float64: (X, Y, Z) = homography @ (x, y, 1) for a target pixel (x, y); the rendered pixel is
    # (X / Z, Y / Z), Z > 0 in front of the rendered eye
    homography: np.ndarray


def _pixel_from_eye(camera: EyeCamera) -> np.ndarray:
    """(3, 3): eye-space direction (x, y, z) -> homogeneous pixel (X, Y, -z) of the camera's image."""
    sx = camera.width / (camera.tan_right - camera.tan_left)
    sy = camera.height / (camera.tan_up - camera.tan_down)
    return np.array([[sx, 0.0, sx * camera.tan_left], [0.0, -sy, -sy * camera.tan_up], [0.0, 0.0, -1.0]])


def _eye_from_pixel(camera: EyeCamera) -> np.ndarray:
    """(3, 3): pixel (x, y, 1) -> its view ray in eye space at unit depth, (tan x, tan y, -1)."""
    sx = (camera.tan_right - camera.tan_left) / camera.width
    sy = (camera.tan_up - camera.tan_down) / camera.height
    return np.array([[sx, 0.0, camera.tan_left], [0.0, -sy, camera.tan_up], [0.0, 0.0, -1.0]])


def homography(rendered: EyeCamera, target: EyeCamera) -> np.ndarray:
    """The rotation-only map from target pixels to homogeneous rendered pixels: the scene at infinity."""
    turn = np.asarray(rendered.rotation, np.float64).T @ np.asarray(target.rotation, np.float64)
    return _pixel_from_eye(rendered) @ turn @ _eye_from_pixel(target)


class Lookups(NamedTuple):
    """One target row's bilinear footprints in the rendered image, one entry per pixel: the flat element index
    of the top-left texel's red channel, the four texels' weights (all 0 behind the rendered eye, so black
    there), and whether the pixel's direction fell on the image."""

    index: np.ndarray  # (w,) int32
    weights: np.ndarray  # (4, w) float32: top-left, top-right, bottom-left, bottom-right
    inside: np.ndarray  # (w,) int32: 1 on the image, 0 off it or behind the rendered eye


@serial
def _lookups(m: np.ndarray, y: int, h: int, row: Lookups) -> None:
    """The footprints of target row y, coordinates clamped to the image so that the edge repeats. float32 and
    stores only, no branches or reductions: the loop vectorises eight pixels wide. Coordinates carry ~1e-4 px
    of float32 rounding at 1280 px; on an unchanged rotation they land on pixel centres exactly."""
    f32, i32 = np.float32, np.int32
    w = len(row.index)
    cy = y + 0.5  # the row's constant terms in float64, then float32 per pixel
    bx = f32(m[0, 0] * 0.5 + m[0, 1] * cy + m[0, 2])
    by = f32(m[1, 0] * 0.5 + m[1, 1] * cy + m[1, 2])
    bz = f32(m[2, 0] * 0.5 + m[2, 1] * cy + m[2, 2])
    m00, m10, m20 = f32(m[0, 0]), f32(m[1, 0]), f32(m[2, 0])
    zero, one, half = f32(0.0), f32(1.0), f32(0.5)
    wf, hf, last_x, last_y = f32(w), f32(h), f32(w - 1), f32(h - 1)
    for x in range(w):
        xf = f32(x)
        z = m20 * xf + bz
        inv = np.divide(one, z)  # a ufunc: no ZeroDivisionError check, which would keep the loop scalar
        qx, qy = (m00 * xf + bx) * inv, (m10 * xf + by) * inv
        front = z > zero
        row.inside[x] = i32(front & (qx >= zero) & (qy >= zero) & (qx < wf) & (qy < hf))
        fx = min(max(qx - half, zero), last_x)  # NaN (z = 0) goes to 0
        fy = min(max(qy - half, zero), last_y)
        ix = max(min(i32(fx), i32(w - 2)), i32(0))  # the footprint's right and lower taps stay inside
        iy = max(min(i32(fy), i32(h - 2)), i32(0))
        ax, ay = fx - f32(ix), fy - f32(iy)
        seen = one if front else zero
        row.weights[0, x], row.weights[1, x] = seen * (one - ax) * (one - ay), seen * ax * (one - ay)
        row.weights[2, x], row.weights[3, x] = seen * (one - ax) * ay, seen * ax * ay
        row.index[x] = (iy * i32(w) + ix) * i32(3)


@serial
def _gather(image: np.ndarray, out: np.ndarray, o: int, row: Lookups) -> int:
    """One target row from its footprints: flat RGB image (h * w * 3,) into flat out from element o, without a
    branch; returns how many of the row's pixels fell on the image. Unsigned indices: numba adds no
    negative-index wraparound to their loads."""
    w = len(row.index)
    h = len(image) // (3 * w)
    step_x = np.uint64(3 if w > 1 else 0)
    step_y = np.uint64(3 * w if h > 1 else 0)
    inside = 0
    for x in range(w):
        j = np.uint64(o + 3 * x)
        inside += row.inside[x]
        k = np.uint64(row.index[x])
        w0, w1, w2, w3 = row.weights[0, x], row.weights[1, x], row.weights[2, x], row.weights[3, x]
        for c in range(3):
            kc = k + np.uint64(c)
            out[j + np.uint64(c)] = (
                w0 * image[kc] + w1 * image[kc + step_x] + w2 * image[kc + step_y] + (w3 * image[kc + step_y + step_x])
            )
    return inside


@serial
def _warp_rows(warp: Warp, y0: int, y1: int) -> int:
    """Warp rows [y0, y1) of warp.out; returns how many of their pixels fell outside the rendered image."""
    h, w = warp.image.shape[0], warp.image.shape[1]
    image, out = warp.image.reshape(-1), warp.out.reshape(-1)
    row = Lookups(np.empty(w, np.int32), np.empty((4, w), np.float32), np.empty(w, np.int32))
    inside = 0
    for y in range(y0, y1):  # a row's footprints stay in cache between the two passes
        _lookups(warp.homography, y, h, row)
        inside += _gather(image, out, y * w * 3, row)
    return (y1 - y0) * w - inside


@kernel
def _warp(warp: Warp, rows_per_block: int) -> int:
    h = warp.image.shape[0]
    blocks = (h + rows_per_block - 1) // rows_per_block
    outside = 0
    for b in nb.prange(blocks):
        outside += _warp_rows(warp, b * rows_per_block, min(h, (b + 1) * rows_per_block))
    return outside


def _check_same_optics(rendered: EyeCamera, target: EyeCamera) -> None:
    a = (rendered.width, rendered.height, rendered.tan_left, rendered.tan_right, rendered.tan_up, rendered.tan_down)
    b = (target.width, target.height, target.tan_left, target.tan_right, target.tan_up, target.tan_down)
    if a[:2] != b[:2] or not np.allclose(a[2:], b[2:], rtol=1e-9, atol=1e-12):
        raise ValueError(
            "timewarp needs the same eye's optics for both cameras: rendered "
            f"{a[0]}x{a[1]} tangents {a[2:]}, target {b[0]}x{b[1]} tangents {b[2:]}"
        )


def timewarp(image: np.ndarray, rendered: EyeCamera, target: EyeCamera, out: np.ndarray | None = None) -> Timewarped:
    """The frame `image` (h, w, 3) linear RGB, rendered with camera `rendered`, as seen from `target`.

    Both cameras must be the same eye (same size and frustum tangents); only their rotations are
    used. Each target pixel centre's direction is projected into the rendered image and sampled
    bilinearly, clamped to the edge outside it (black behind the rendered eye). Pass `out`, a C-contiguous
    (h, w, 3) float32 array not overlapping `image`, to reuse a buffer. An identical rotation returns
    the image to within float32 rounding (the homography's float64 rounding vanishes in float32 lookups).
    """
    _check_same_optics(rendered, target)
    if image.shape != (rendered.height, rendered.width, 3):
        raise ValueError(f"image must be ({rendered.height}, {rendered.width}, 3) for the camera, got {image.shape}")
    if image.size > np.iinfo(np.int32).max:
        raise ValueError(f"image of {image.size} values: the warp indexes at most 2**31 - 1 (int32 lookups)")
    image = np.ascontiguousarray(image, dtype=np.float32)
    if out is None:
        out = np.empty_like(image)
    elif out.shape != image.shape or out.dtype != np.float32 or not out.flags.c_contiguous:
        raise ValueError(
            f"out must be a C-contiguous float32 array of shape {image.shape}, got {out.dtype} {out.shape}"
        )
    elif np.shares_memory(out, image):
        raise ValueError("out must not overlap image: the warp reads pixels it would already have overwritten")
    rows_per_block = max(1, ROWS_PIXELS // rendered.width)
    outside = _warp(Warp(image, out, homography(rendered, target)), rows_per_block)
    return Timewarped(out, float(outside) / (rendered.width * rendered.height))
