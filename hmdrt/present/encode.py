"""Linear float32 RGB to 8-bit sRGB (one fused pass per image, eyes side by side), and PNG output.

Values outside [0, 1] are clipped by the display encoding, as a display would; that is output
quantisation, not input clamping.
"""

from __future__ import annotations

import math
from pathlib import Path

import numba as nb
import numpy as np
from PIL import Image

from hmdrt.errors import HmdrtError
from hmdrt.jit import inline, kernel


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
    images = [np.ascontiguousarray(image, dtype=np.float32) for image in images]
    shape = (images[0].shape[0], sum(image.shape[1] for image in images), 3)
    if out is None:
        out = np.empty(shape, np.uint8)
    elif out.shape != shape or out.dtype != np.uint8:
        raise ValueError(f"out must be a uint8 array of shape {shape}, got {out.dtype} {out.shape}")
    x0 = 0
    for image in images:
        _encode_into(image, out, x0)
        x0 += image.shape[1]
    return out


def linear_to_srgb8(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) linear float -> (h, w, 3) uint8 sRGB."""
    return side_by_side_srgb8([image])


def write_png(path: str | Path, srgb8: np.ndarray) -> None:
    """Write an (h, w, 3) uint8 image as PNG, creating parent folders."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(srgb8, mode="RGB").save(path, format="PNG")
    except (OSError, ValueError) as exc:
        raise HmdrtError(f"cannot write {path}: {exc}") from None
