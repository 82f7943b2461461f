"""Image error by eccentricity band (kim2021 section 5 reports PSNR per band of the central region): PSNR,
SSIM (Wang et al. 2004) and temporal instability (flicker), per frame or pooled over a sequence."""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import gaussian_filter

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


SSIM_SIGMA = 1.5  # Wang et al. 2004: an 11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03, on luminance
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2
LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)  # Rec. 709 luminance of linear RGB


def band_masks(eccentricity: np.ndarray) -> dict[str, np.ndarray]:
    """Pixel masks of each band of BANDS, and "image" for all pixels."""
    masks = {name: (eccentricity >= lo) & (eccentricity < hi) for name, (lo, hi) in BANDS.items()}
    masks["image"] = np.ones(eccentricity.shape, dtype=bool)
    return masks


def luminance(image: np.ndarray) -> np.ndarray:
    """Luminance (h, w) float32 of a linear RGB image clipped to [0, 1]."""
    return np.clip(image, 0.0, 1.0, dtype=np.float32) @ LUMA


def ssim_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (h, w) of the luminance of two linear RGB images, data range 1, windows truncated at 3.5
    sigma (11 x 11) and mirrored at the borders."""
    x, y = luminance(image).astype(np.float64), luminance(reference).astype(np.float64)

    def blur(a: np.ndarray) -> np.ndarray:
        return gaussian_filter(a, SSIM_SIGMA, truncate=3.5, mode="mirror")

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    return ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)) / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))


class BandScores:
    """Per-band error of a rendered sequence against its ground truth, pooled over the frames added:
    PSNR from the mean squared error over all the frames' pixels in the band, SSIM as the mean of the SSIM
    map there, and flicker as the mean absolute frame-to-frame change of the method's images beyond that
    of the ground truth's (0: as steady as the truth; bands are those of the later frame's gaze)."""

    def __init__(self) -> None:
        names = (*BANDS, "image")
        self._sse = dict.fromkeys(names, 0.0)
        self._ssim = dict.fromkeys(names, 0.0)
        self._change = dict.fromkeys(names, 0.0)
        self._truth_change = dict.fromkeys(names, 0.0)
        self._pixels = dict.fromkeys(names, 0)
        self._pairs = dict.fromkeys(names, 0)
        self._previous: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, image: np.ndarray, truth: np.ndarray, eccentricity: np.ndarray) -> None:
        a = np.clip(image, 0.0, 1.0, dtype=np.float32)
        b = np.clip(truth, 0.0, 1.0, dtype=np.float32)
        squared = ((a - b) ** 2).sum(axis=2, dtype=np.float64)
        ssim = ssim_map(a, b)
        change = truth_change = None
        if self._previous is not None:
            change = np.abs(a - self._previous[0]).mean(axis=2)
            truth_change = np.abs(b - self._previous[1]).mean(axis=2)
        for name, mask in band_masks(eccentricity).items():
            n = int(mask.sum())
            self._pixels[name] += n
            self._sse[name] += float(squared[mask].sum())
            self._ssim[name] += float(ssim[mask].sum())
            if change is not None:
                self._pairs[name] += n
                self._change[name] += float(change[mask].sum())
                self._truth_change[name] += float(truth_change[mask].sum())
        self._previous = (a, b)

    def result(self) -> dict[str, float | None]:
        """psnr_BAND (dB), ssim_BAND and flicker_BAND for each band and "image"; None where no pixel fell."""
        out: dict[str, float | None] = {}
        for name, n in self._pixels.items():
            mse = self._sse[name] / (3 * n) if n else None
            out[f"psnr_{name}"] = None if mse is None else math.inf if mse == 0 else 10 * math.log10(1.0 / mse)
            out[f"ssim_{name}"] = self._ssim[name] / n if n else None
        for name, n in self._pairs.items():
            out[f"flicker_{name}"] = (self._change[name] - self._truth_change[name]) / n if n else None
        return out
