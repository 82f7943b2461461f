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
kernel per eye into the caller's buffer. Per row it projects every pixel in float32 vectors (_lookups), then
blends each pixel's four texels with SIMD loads of whole texels from the interleaved RGB image (_bilerp: four
16-byte loads, three lerps, one 12-byte store), since numba leaves a blend of 12 floats written per channel
scalar (docs/performance.md, bench/timewarp.py).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from hmdrt.kernels.jit import kernel, serial
from hmdrt.kernels.simd import lerp, pick, prefetch, splat, vector_at
from hmdrt.optics.camera import EyeCamera


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
    of the top-left texel's red channel, the fractions towards the right and lower texels, and whether the
    pixel's direction fell on the image; with the row's column numbers as float32, which the lookups read
    rather than convert from the int64 loop counter (a conversion that halves their vector width)."""

    index: np.ndarray  # (w,) int32
    ax: np.ndarray  # (w,) float32 in [0, 1]
    ay: np.ndarray  # (w,) float32 in [0, 1]
    inside: np.ndarray  # (w,) uint8: 1 on the image, 0 off it or behind the rendered eye
    columns: np.ndarray  # (w,) float32: 0, 1, ..., w - 1


@serial
def _row_terms(m: np.ndarray, y: int) -> tuple:
    """The float32 terms of target row y's projection, (X, Y, Z) = (m00, m10, m20) * x + (bx, by, bz) for column x:
    the row's constant terms summed in float64 (pixel centres at + 0.5), then the per-pixel steps in float32."""
    f32 = np.float32
    cy = y + 0.5
    bx = f32(m[0, 0] * 0.5 + m[0, 1] * cy + m[0, 2])
    by = f32(m[1, 0] * 0.5 + m[1, 1] * cy + m[1, 2])
    bz = f32(m[2, 0] * 0.5 + m[2, 1] * cy + m[2, 2])
    return f32(m[0, 0]), f32(m[1, 0]), f32(m[2, 0]), bx, by, bz


@serial
def _lookups(m: np.ndarray, y: int, h: int, row: Lookups) -> int:
    """The footprints of target row y, coordinates clamped to the image so that the edge repeats; returns how many
    of the row's pixels fell on the image. float32 and stores only, no branches or reductions: the loop
    vectorises eight pixels wide (the count is a second loop, over the row's flags). Coordinates carry ~1e-4 px
    of float32 rounding at 1280 px; on an unchanged rotation they land on pixel centres exactly."""
    f32, i32 = np.float32, np.int32
    w = len(row.index)
    m00, m10, m20, bx, by, bz = _row_terms(m, y)
    zero, one, half = f32(0.0), f32(1.0), f32(0.5)
    wf, hf, last_x, last_y = f32(w), f32(h), f32(w - 1), f32(h - 1)
    for x in range(w):
        xf = row.columns[x]
        z = m20 * xf + bz
        inv = np.divide(one, z)  # a ufunc: no ZeroDivisionError check, which would keep the loop scalar
        qx, qy = (m00 * xf + bx) * inv, (m10 * xf + by) * inv
        row.inside[x] = np.uint8((z > zero) & (qx >= zero) & (qy >= zero) & (qx < wf) & (qy < hf))
        fx = min(max(qx - half, zero), last_x)  # NaN (z = 0) goes to 0
        fy = min(max(qy - half, zero), last_y)
        ix = max(min(i32(fx), i32(w - 2)), i32(0))  # the footprint's right and lower taps stay inside
        iy = max(min(i32(fy), i32(h - 2)), i32(0))
        row.ax[x], row.ay[x] = fx - f32(ix), fy - f32(iy)
        row.index[x] = (iy * i32(w) + ix) * i32(3)
    inside = 0
    for x in range(w):
        inside += row.inside[x]
    return inside


@serial
def _black_behind(m: np.ndarray, y: int, out: np.ndarray, o: int, columns: np.ndarray) -> None:
    """Black for the pixels of target row y (from element o of flat out) that look behind the rendered eye (Z not
    above 0, as _lookups computes it). Z is monotonic along a row (a float32 product and sum of the column, each
    rounded monotonically), so a row whose two ends are in front is in front throughout and is left as it is."""
    _, _, m20, _, _, bz = _row_terms(m, y)
    zero, w = np.float32(0.0), len(columns)
    if m20 * columns[0] + bz > zero and m20 * columns[w - 1] + bz > zero:
        return
    for x in range(w):
        if not m20 * columns[x] + bz > zero:
            out[o + 3 * x : o + 3 * x + 3] = 0.0


def _make_bilerp(pairs: bool) -> object:
    """The intrinsic bilerp(image, out, k, j, step_x, step_y, ax, ay): one pixel's bilinear blend of the four RGB
    texels from flat element k (right: + step_x, lower: + step_y) stored at flat element j of out, each texel one
    SIMD load and the pixel one store (numba, SLP vectorisation off, would load and blend the 12 floats one by one).

    pairs: the image is at least two pixels wide and each row's two texels are loaded as four floats from k and
    from k + 2 (a texel and the next one's red; the first one's blue and the next texel), four loads that never
    reach past the right texel, then one shuffle; and the texel a row below the lower one is prefetched, the one
    the next target row reads. A target row's footprints cross 15-20 texel rows where the turned rows bend, each
    crossing a new stream that the hardware prefetcher takes a few misses to find: on the AMD EPYC the prefetch took
    both eyes at 640x720 from 3.2-3.9 to 2.3-2.5 ms on one thread. Otherwise each texel is loaded as three floats
    (x86 takes two loads for three), which 1-pixel-wide images need (step_x 0)."""

    def signature(typingctx, image, out, k, j, step_x, step_y, ax, ay):
        def codegen(context, builder, sig, args):
            src = context.make_array(sig.args[0])(context, builder, args[0]).data
            dst = context.make_array(sig.args[1])(context, builder, args[1]).data
            k, j, step_x, step_y, ax, ay = args[2:]
            lower = builder.add(k, step_y)
            if pairs:
                two = ir.Constant(ir.IntType(64), 2)
                prefetch(builder, src, builder.add(lower, step_y))
                top, top_right = (
                    builder.load(vector_at(builder, src, i, 4), align=4) for i in (k, builder.add(k, two))
                )
                low, low_right = (
                    builder.load(vector_at(builder, src, i, 4), align=4) for i in (lower, builder.add(lower, two))
                )
                ay4 = splat(builder, ay, 4)
                left, right = (
                    lerp(builder, top, low, ay4),
                    pick(builder, lerp(builder, top_right, low_right, ay4), [1, 2, 3, 3]),
                )
                blend = pick(builder, lerp(builder, left, right, splat(builder, ax, 4)), [0, 1, 2])
            else:
                taps = [k, builder.add(k, step_x), lower, builder.add(lower, step_x)]
                tl, tr, bl, br = (builder.load(vector_at(builder, src, i, 3), align=4) for i in taps)
                ay3 = splat(builder, ay, 3)
                blend = lerp(builder, lerp(builder, tl, bl, ay3), lerp(builder, tr, br, ay3), splat(builder, ax, 3))
            builder.store(blend, vector_at(builder, dst, j, 3), align=4)
            return context.get_dummy_value()

        i64, f32 = types.int64, types.float32
        return types.void(image, out, i64, i64, i64, i64, f32, f32), codegen

    return intrinsic(signature)


_bilerp_pairs, _bilerp_texels = _make_bilerp(True), _make_bilerp(False)


@serial
def _gather(image: np.ndarray, out: np.ndarray, o: int, row: Lookups) -> None:
    """One target row from its footprints: flat RGB image (h * w * 3,) into flat out from element o, every read
    inside the image (an image 1 pixel tall reads its row twice: step_y 0)."""
    w = len(row.index)
    h = len(image) // (3 * w)
    step_x, step_y = np.int64(3 if w > 1 else 0), np.int64(3 * w if h > 1 else 0)
    for x in range(w):  # the branch is the same for every pixel: LLVM takes it out of the loop
        k, j, ax, ay = np.int64(row.index[x]), np.int64(o + 3 * x), row.ax[x], row.ay[x]
        if w > 1:
            _bilerp_pairs(image, out, k, j, step_x, step_y, ax, ay)
        else:
            _bilerp_texels(image, out, k, j, step_x, step_y, ax, ay)


@serial
def _warp_rows(warp: Warp, y0: int, y1: int) -> int:
    """Warp rows [y0, y1) of warp.out; returns how many of their pixels fell outside the rendered image."""
    h, w = warp.image.shape[0], warp.image.shape[1]
    image, out = warp.image.reshape(-1), warp.out.reshape(-1)
    columns = np.arange(w, dtype=np.float32)
    row = Lookups(
        np.empty(w, np.int32), np.empty(w, np.float32), np.empty(w, np.float32), np.empty(w, np.uint8), columns
    )
    inside = 0
    for y in range(y0, y1):  # a row's footprints stay in cache between the passes
        inside += _lookups(warp.homography, y, h, row)
        _gather(image, out, y * w * 3, row)
        _black_behind(warp.homography, y, out, y * w * 3, columns)
    return (y1 - y0) * w - inside


@kernel
def _warp(warp: Warp, blocks: int) -> int:
    """warp.out from warp.image in `blocks` bands of rows, one per thread (numba deals a prange out in contiguous
    shares, and every row costs about the same); returns how many pixels fell outside the rendered image."""
    h = warp.image.shape[0]
    rows = (h + blocks - 1) // blocks
    outside = 0
    for b in nb.prange(blocks):
        outside += _warp_rows(warp, min(h, b * rows), min(h, (b + 1) * rows))
    return outside


def _check_same_optics(rendered: EyeCamera, target: EyeCamera) -> None:
    a = (rendered.width, rendered.height, rendered.tan_left, rendered.tan_right, rendered.tan_up, rendered.tan_down)
    b = (target.width, target.height, target.tan_left, target.tan_right, target.tan_up, target.tan_down)
    close = (math.isclose(p, q, rel_tol=1e-9, abs_tol=1e-12) for p, q in zip(a[2:], b[2:], strict=True))
    if a[:2] != b[:2] or not all(close):  # math.isclose: np.allclose took 15 us of a call, twice per VSync
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
    the image exactly (the homography's float64 rounding vanishes in float32 lookups, which land on pixel
    centres); otherwise values in [0, 1] come out within 1e-6 of a float64 blend of the same float32 lookups
    (the multiply-adds are fused where the CPU has FMA, so the last bit may differ between machines).
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
    blocks = min(rendered.height, nb.get_num_threads())  # read here: in the kernel it would keep it from caching
    outside = _warp(Warp(image, out, homography(rendered, target)), blocks)
    return Timewarped(out, float(outside) / (rendered.width * rendered.height))
