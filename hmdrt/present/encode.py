"""Linear float32 RGB to 8-bit sRGB (one fused pass), and PNG output.

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


@nb.njit(parallel=True, cache=True, nogil=True)
def _encode(flat, out):
    for i in nb.prange(flat.shape[0]):
        x = flat[i]
        if not x > 0.0:  # also catches NaN
            out[i] = 0
        elif x >= 1.0:
            out[i] = 255
        else:
            s = 12.92 * x if x <= 0.0031308 else 1.055 * math.pow(x, 1.0 / 2.4) - 0.055
            out[i] = np.uint8(s * 255.0 + 0.5)


def linear_to_srgb8(image: np.ndarray) -> np.ndarray:
    """(h, w, 3) linear float -> (h, w, 3) uint8 sRGB."""
    flat = np.ascontiguousarray(image, dtype=np.float32).reshape(-1)
    out = np.empty(flat.shape, dtype=np.uint8)
    _encode(flat, out)
    return out.reshape(image.shape)


def write_png(path: str | Path, srgb8: np.ndarray) -> None:
    """Write an (h, w, 3) uint8 image as PNG, creating parent folders."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        Image.fromarray(srgb8, mode="RGB").save(path, format="PNG")
    except (OSError, ValueError) as exc:
        raise HmdrtError(f"cannot write {path}: {exc}") from None
