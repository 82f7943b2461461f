"""Linear float32 RGB to 8-bit sRGB (one fused pass per image, eyes side by side), shrunk previews of it, and PNG
output.

Values outside [0, 1] are clipped by the display encoding, as a display would; that is output
quantisation, not input clamping.
"""

from __future__ import annotations

import io
import math
from collections.abc import Callable
from functools import cache
from pathlib import Path

import numba as nb
import numpy as np
from PIL import Image

from hmdrt.errors import HmdrtError
from hmdrt.files.atomic import write_atomic
from hmdrt.kernels.jit import inline, kernel

PREVIEW_LEVELS = 16384  # linear levels of preview_srgb8's table: steps of at most one sRGB code


@inline
def _srgb8(x: float) -> np.uint8:
    if not x > 0.0:  # also catches NaN
        return np.uint8(0)
    if x >= 1.0:
        return np.uint8(255)
    s = 12.92 * x if x <= 0.0031308 else 1.055 * math.pow(x, 1.0 / 2.4) - 0.055
    return np.uint8(s * 255.0 + 0.5)


@kernel
def _encode_into(image: np.ndarray, out: np.ndarray, x0: int) -> None:
    """image (h, w, 3) float32 into columns [x0, x0 + w) of out (h, W, 3) uint8."""
    h, w = image.shape[0], image.shape[1]
    for y in nb.prange(h):
        for x in range(w):
            for c in range(3):
                out[y, x0 + x, c] = _srgb8(image[y, x, c])


def side_by_side_srgb8(images: list[np.ndarray], out: np.ndarray | None = None) -> np.ndarray:
    """(h, w, 3) linear float images of one height, left to right, as one (h, sum of w, 3) uint8 sRGB image: each
    encoded where it goes, never joined as floats first. `out`, when given, is that uint8 image, written and
    returned."""
    return _side_by_side(images, 1, out, _encode_into)


def _side_by_side(
    images: list[np.ndarray], factor: int, out: np.ndarray | None, encode: Callable[[np.ndarray, np.ndarray, int], None]
) -> np.ndarray:
    """The images, each shrunk by `factor`, left to right in one uint8 image (out, or a new one): encode(image, out,
    x0) writes one image from column x0."""
    images = [np.ascontiguousarray(image, dtype=np.float32) for image in images]
    shape = (images[0].shape[0] // factor, sum(image.shape[1] // factor for image in images), 3)
    if out is None:
        out = np.empty(shape, np.uint8)
    elif out.shape != shape or out.dtype != np.uint8:
        raise ValueError(f"out must be a uint8 array of shape {shape}, got {out.dtype} {out.shape}")
    x0 = 0
    for image in images:
        encode(image, out, x0)
        x0 += image.shape[1] // factor
    return out


@kernel
def _shrink_into(image: np.ndarray, out: np.ndarray, x0: int, factor: int, levels: np.ndarray) -> None:
    """image (h, w, 3) float32, each factor x factor block averaged in linear light and looked up in `levels` (the
    sRGB codes of len(levels) evenly spaced linear values), into columns [x0, x0 + w // factor) of out."""
    h, w, top = image.shape[0] // factor, image.shape[1] // factor, len(levels) - 1
    scale = np.float32(top / (factor * factor))
    for y in nb.prange(h):
        for x in range(w):
            for c in range(3):
                total = np.float32(0.0)
                for dy in range(factor):
                    for dx in range(factor):
                        total += image[y * factor + dy, x * factor + dx, c]
                level = total * scale + np.float32(0.5)
                if not level > 0.0:  # also NaN
                    out[y, x0 + x, c] = levels[0]
                elif level >= top:  # also inf
                    out[y, x0 + x, c] = levels[top]
                else:
                    out[y, x0 + x, c] = levels[int(level)]


@cache
def _srgb_levels() -> np.ndarray:
    """The sRGB code of each of PREVIEW_LEVELS evenly spaced linear values in [0, 1], as _srgb8 encodes them."""
    ramp = np.repeat(np.linspace(0.0, 1.0, PREVIEW_LEVELS, dtype=np.float32)[None, :, None], 3, axis=2)
    return np.ascontiguousarray(side_by_side_srgb8([ramp])[0, :, 0])


def preview_srgb8(images: list[np.ndarray], factor: int, out: np.ndarray | None = None) -> np.ndarray:
    """side_by_side_srgb8 of the images shrunk by `factor` (the mean of each factor x factor block, in linear light;
    a remainder of rows or columns left out), through a table of PREVIEW_LEVELS linear levels: within one code
    value of the exact encoding of the means, several times faster, for previews."""
    levels = _srgb_levels()
    return _side_by_side(images, factor, out, lambda image, into, x0: _shrink_into(image, into, x0, factor, levels))


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
