"""Linear float32 RGB to 8-bit sRGB (one fused pass per image, eyes side by side), shrunk previews of it, and PNG
output.

Values outside [0, 1] are clipped by the display encoding, as a display would; that is output
quantisation, not input clamping.

The sRGB transfer function (_srgb8, a float64 pow per channel) took 34 ms for both eyes at 640x720 on one thread,
about 12 ns a value, so the kernels never call it: they look the code up instead (_lookup), exactly. The value's
bucket of 1/BUCKETS in linear light gives the code at the bucket's start, and one comparison with the next code's
threshold (the least float32 _srgb8 maps to that code) adds 1 or not: no bucket holds two thresholds, since the
codes are at least 1/3295 apart in linear light (the steepest part of the curve, 12.92 x 255 codes per unit) and a
bucket is 1/4096 wide. So every float32 gets the code _srgb8 gives it, and the PNGs are as they were
(test_preview checks every threshold and every bucket's edges, and with -m slow every float32 of [0, 1]).
"""

from __future__ import annotations

import io
import math
from functools import cache
from pathlib import Path
from typing import NamedTuple

import numba as nb
import numpy as np
from PIL import Image

from hmdrt.errors import HmdrtError
from hmdrt.files.atomic import write_atomic
from hmdrt.kernels.jit import inline, kernel, serial

BUCKETS = 4096  # linear-light buckets of the lookup: narrower than the closest two sRGB codes' thresholds


class Tables(NamedTuple):
    """The lookup of _srgb8: codes[i] is the code of i / BUCKETS; limits[k] the least float32 whose code is k
    (limits[0] 0, limits[256] infinity, so that code 255 never steps past itself)."""

    codes: np.ndarray  # (BUCKETS,) uint8
    limits: np.ndarray  # (257,) float32


@inline
def _srgb8(x: float) -> np.uint8:
    """The exact sRGB encoding, in float64, rounded to the nearest code: the definition the tables are made from."""
    if not x > 0.0:  # also catches NaN
        return np.uint8(0)
    if x >= 1.0:
        return np.uint8(255)
    s = 12.92 * x if x <= 0.0031308 else 1.055 * math.pow(x, 1.0 / 2.4) - 0.055
    return np.uint8(s * 255.0 + 0.5)


@serial
def _srgb8_each(values: np.ndarray, out: np.ndarray) -> None:
    """_srgb8 of each float32 value, into out: to make the tables and to check them."""
    for i in range(values.shape[0]):
        out[i] = _srgb8(values[i])


@cache
def tables() -> Tables:
    """The lookup's tables, made once from _srgb8: each code's threshold by bisection over the float32 bit patterns
    of [0, 1] (ordered as integers since they are positive), all codes at once; sound as _srgb8 never decreases."""
    codes = np.empty(BUCKETS, np.uint8)
    _srgb8_each(np.arange(BUCKETS, dtype=np.float32) / np.float32(BUCKETS), codes)
    wanted = np.arange(1, 256, dtype=np.uint8)
    lo = np.zeros(255, np.int32)  # code < wanted
    hi = np.full(255, np.float32(1.0).view(np.int32), np.int32)  # code >= wanted
    got = np.empty(255, np.uint8)
    while (hi - lo > 1).any():
        mid = lo + (hi - lo) // 2
        _srgb8_each(mid.view(np.float32), got)
        high = got >= wanted
        hi, lo = np.where(high, mid, hi), np.where(high, lo, mid)
    limits = np.concatenate([[0], hi.view(np.float32), [np.inf]]).astype(np.float32)
    return Tables(codes, limits)


@inline
def _lookup(x: np.float32, codes: np.ndarray, limits: np.ndarray) -> np.uint8:
    """_srgb8(x) of a float32 x through the tables: a bucket's code, plus 1 if x reaches the next code's threshold."""
    if not x > 0.0:  # also NaN
        return np.uint8(0)
    if x >= 1.0:  # also inf
        return np.uint8(255)
    code = codes[np.int32(x * np.float32(BUCKETS))]
    return code + np.uint8(x >= limits[code + 1])


@kernel
def _encode_into(image: np.ndarray, out: np.ndarray, x0: int, codes: np.ndarray, limits: np.ndarray) -> None:
    """image (h, w, 3) float32 into columns [x0, x0 + w) of out (h, W, 3) uint8."""
    h, w = image.shape[0], image.shape[1]
    for y in nb.prange(h):
        for x in range(w):
            for c in range(3):
                out[y, x0 + x, c] = _lookup(image[y, x, c], codes, limits)


@kernel
def _shrink_into(
    image: np.ndarray, out: np.ndarray, x0: int, factor: int, codes: np.ndarray, limits: np.ndarray
) -> None:
    """image (h, w, 3) float32, the mean of each factor x factor block in linear light (float32, summed row by row
    in memory order), encoded into columns [x0, x0 + w // factor) of out. Factor 2 (the watch's at sim-cpu-640) has
    a path of its own with the same sums: with the block's size known, it takes 1.2 ms for both eyes where the
    general loop takes 1.6 (bench/preview.py)."""
    h, w = image.shape[0] // factor, image.shape[1] // factor
    scale = np.float32(1.0 / (factor * factor))
    for y in nb.prange(h):
        if factor == 2:
            top, bottom = image[2 * y], image[2 * y + 1]
            for x in range(w):
                for c in range(3):
                    total = top[2 * x, c] + top[2 * x + 1, c] + bottom[2 * x, c] + bottom[2 * x + 1, c]
                    out[y, x0 + x, c] = _lookup(total * scale, codes, limits)
            continue
        for x in range(w):
            r, g, b = np.float32(0.0), np.float32(0.0), np.float32(0.0)
            for dy in range(factor):
                for dx in range(factor):
                    r += image[y * factor + dy, x * factor + dx, 0]
                    g += image[y * factor + dy, x * factor + dx, 1]
                    b += image[y * factor + dy, x * factor + dx, 2]
            out[y, x0 + x, 0] = _lookup(r * scale, codes, limits)
            out[y, x0 + x, 1] = _lookup(g * scale, codes, limits)
            out[y, x0 + x, 2] = _lookup(b * scale, codes, limits)


def _side_by_side(images: list[np.ndarray], factor: int, out: np.ndarray | None) -> np.ndarray:
    """The images, each shrunk by `factor` (1: as they are), left to right in one uint8 image (out, or a new one)."""
    images = [np.ascontiguousarray(image, dtype=np.float32) for image in images]
    shape = (images[0].shape[0] // factor, sum(image.shape[1] // factor for image in images), 3)
    if out is None:
        out = np.empty(shape, np.uint8)
    elif out.shape != shape or out.dtype != np.uint8:
        raise ValueError(f"out must be a uint8 array of shape {shape}, got {out.dtype} {out.shape}")
    codes, limits = tables()
    x0 = 0
    for image in images:
        if factor == 1:
            _encode_into(image, out, x0, codes, limits)
        else:
            _shrink_into(image, out, x0, factor, codes, limits)
        x0 += image.shape[1] // factor
    return out


def side_by_side_srgb8(images: list[np.ndarray], out: np.ndarray | None = None) -> np.ndarray:
    """(h, w, 3) linear float images of one height, left to right, as one (h, sum of w, 3) uint8 sRGB image: each
    encoded where it goes, never joined as floats first. `out`, when given, is that uint8 image, written and
    returned."""
    return _side_by_side(images, 1, out)


def preview_srgb8(images: list[np.ndarray], factor: int, out: np.ndarray | None = None) -> np.ndarray:
    """side_by_side_srgb8 of the images shrunk by `factor` (the float32 mean of each factor x factor block, in linear
    light; a remainder of rows or columns left out), in one pass that reads each image once: the exact encoding of
    those means, for previews."""
    return _side_by_side(images, factor, out)


def linear_to_srgb8(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) linear float -> (h, w, 3) uint8 sRGB."""
    return side_by_side_srgb8([image])


def write_png(path: str | Path, srgb8: np.ndarray, replace: bool = True) -> None:
    """Write an (h, w, 3) uint8 image as PNG, creating parent folders, whole or not at all and never through a link
    (hmdrt.files.atomic). replace=False: FileExistsError when something (also a link) has the name, checked and
    created in one step, so nothing is overwritten."""
    png = io.BytesIO()
    try:
        Image.fromarray(srgb8, mode="RGB").save(png, format="PNG")
    except (OSError, ValueError) as exc:
        raise HmdrtError(f"cannot write {path}: {exc}") from None
    write_atomic(path, png.getvalue(), replace=replace, sync=False)
