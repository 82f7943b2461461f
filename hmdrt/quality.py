"""Image error by eccentricity band (kim2021 section 5 reports PSNR per band of the central region)."""

from __future__ import annotations

import math

import numpy as np

# kim2021's band edges in degrees: fovea < e_f, parafovea < e_p, perifovea < e_m, near periphery < e_np
BANDS = {
    "fovea": (0.0, 3.3),
    "parafovea": (3.3, 5.5),
    "perifovea": (5.5, 12.1),
    "near_periphery": (12.1, 30.0),
    "far_periphery": (30.0, math.inf),
}


def psnr(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of linear images clipped to [0, peak], over the masked pixels."""
    a = np.clip(image, 0.0, peak).astype(np.float64)
    b = np.clip(reference, 0.0, peak).astype(np.float64)
    diff = (a - b) ** 2
    mse = float(diff[mask].mean()) if mask is not None else float(diff.mean())
    if mask is not None and not mask.any():
        return math.nan
    return math.inf if mse == 0.0 else 10.0 * math.log10(peak * peak / mse)


def band_psnr(image: np.ndarray, reference: np.ndarray, eccentricity: np.ndarray) -> dict[str, float]:
    """PSNR per eccentricity band and over the whole image."""
    out = {name: psnr(image, reference, (eccentricity >= lo) & (eccentricity < hi)) for name, (lo, hi) in BANDS.items()}
    out["image"] = psnr(image, reference)
    return out
