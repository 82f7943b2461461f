"""Image error by eccentricity band (kim2021 section 5 reports PSNR per band of the central region): PSNR,
SSIM (Wang et al. 2004) and temporal instability (flicker), per frame or pooled over a sequence.

The functions score images in whichever space they are given, clipped to [0, 1]: linear radiance, or display
encoded (to_space); BandScores encodes what it is given into its space first.
"""

from __future__ import annotations

import math
from typing import Literal

import numba as nb
import numpy as np
from scipy.ndimage import gaussian_filter

from hmdrt.kernels.jit import kernel

# kim2021's band edges in degrees: fovea < e_f, parafovea < e_p, perifovea < e_m, near periphery < e_np
BANDS = {
    "fovea": (0.0, 3.3),
    "parafovea": (3.3, 5.5),
    "perifovea": (5.5, 12.1),
    "near_periphery": (12.1, 30.0),
    "far_periphery": (30.0, math.inf),
}

ScoreSpace = Literal["srgb", "linear"]  # display-encoded (the image a viewer sees), or linear radiance
SPACE_NAMES: dict[ScoreSpace, str] = {"srgb": "display-encoded (sRGB)", "linear": "linear radiance"}


def srgb_encode(image: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values clipped to [0, 1]: float32, not quantised."""
    image = np.ascontiguousarray(image, dtype=np.float32)
    out = np.empty_like(image)
    _srgb_encode(image, out)
    return out


@kernel
def _srgb_encode(image: np.ndarray, out: np.ndarray) -> None:
    flat, encoded = image.reshape(-1), out.reshape(-1)
    one, knee = np.float32(1.0), np.float32(0.0031308)  # float32 constants: float64 ones triple its time
    for i in nb.prange(flat.size):
        x = flat[i]
        if not x > knee:  # also NaN, which stays NaN as np.clip leaves it
            encoded[i] = np.float32(12.92) * max(x, np.float32(0.0))
        elif x >= one:
            encoded[i] = one
        else:
            encoded[i] = np.float32(1.055) * x ** np.float32(1 / 2.4) - np.float32(0.055)


def to_space(image: np.ndarray, space: ScoreSpace) -> np.ndarray:
    """A linear RGB image as scored in `space`: float32 in [0, 1], clipped, and sRGB-encoded for "srgb"."""
    return srgb_encode(image) if space == "srgb" else np.clip(image, 0.0, 1.0, dtype=np.float32)


def psnr(image: np.ndarray, reference: np.ndarray, mask: np.ndarray | None = None, peak: float = 1.0) -> float:
    """Peak signal-to-noise ratio in dB of two images in one space, clipped to [0, peak], over the masked pixels."""
    if mask is not None and not mask.any():
        return math.nan
    a = np.clip(image, 0.0, peak).astype(np.float64)
    b = np.clip(reference, 0.0, peak).astype(np.float64)
    diff = (a - b) ** 2
    mse = float(diff[mask].mean()) if mask is not None else float(diff.mean())
    return math.inf if mse == 0.0 else 10.0 * math.log10(peak * peak / mse)


def band_psnr(image: np.ndarray, reference: np.ndarray, eccentricity: np.ndarray) -> dict[str, float]:
    """PSNR per eccentricity band and over the whole image."""
    out = {name: psnr(image, reference, (eccentricity >= lo) & (eccentricity < hi)) for name, (lo, hi) in BANDS.items()}
    out["image"] = psnr(image, reference)
    return out


SSIM_SIGMA = 1.5  # Wang et al. 2004: an 11x11 Gaussian window, sigma 1.5, K1 0.01, K2 0.03, on luminance
SSIM_C1, SSIM_C2 = 0.01**2, 0.03**2
LUMA = np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)  # Rec. 709 weights: luminance of linear RGB, luma of sRGB


def band_index(eccentricity: np.ndarray) -> np.ndarray:
    """Each pixel's band as its index in BANDS, flattened (int64); len(BANDS) for a pixel in none (NaN)."""
    edges = np.array([lo for lo, _ in BANDS.values()], dtype=np.float64)
    index = np.searchsorted(edges, eccentricity.ravel(), side="right") - 1
    index[(index < 0) | np.isnan(eccentricity.ravel())] = len(BANDS)
    return index


def luminance(image: np.ndarray) -> np.ndarray:
    """Luminance (h, w) float32 of an RGB image clipped to [0, 1] (luma when the image is sRGB-encoded)."""
    return np.clip(image, 0.0, 1.0, dtype=np.float32) @ LUMA


def ssim_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM (h, w) of the luminance of two RGB images in one space, data range 1, windows truncated at
    3.5 sigma (11 x 11) and mirrored at the borders."""
    x, y = luminance(image).astype(np.float64), luminance(reference).astype(np.float64)

    def blur(a: np.ndarray) -> np.ndarray:
        return gaussian_filter(a, SSIM_SIGMA, truncate=3.5, mode="mirror")

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx * mx, blur(y * y) - my * my, blur(x * y) - mx * my
    return ((2 * mx * my + SSIM_C1) * (2 * cxy + SSIM_C2)) / ((mx * mx + my * my + SSIM_C1) * (vx + vy + SSIM_C2))


class BandScores:
    """Per-band error of a rendered sequence against its ground truth, both linear, scored in `space`, pooled over
    the frames added: PSNR from the mean squared error over all the frames' pixels in the band, SSIM as the mean of
    the SSIM map there, and flicker as the mean absolute difference between the method's frame-to-frame change and
    the truth's (0: it changes as the truth does; a frozen image under a moving truth scores its motion). Bands are
    those of the later frame's gaze."""

    def __init__(self, space: ScoreSpace = "srgb") -> None:
        self.space = space
        names = (*BANDS, "image")
        self._sse = dict.fromkeys(names, 0.0)
        self._ssim = dict.fromkeys(names, 0.0)
        self._flicker = dict.fromkeys(names, 0.0)
        self._pixels = dict.fromkeys(names, 0)
        self._pairs = dict.fromkeys(names, 0)
        self._previous: tuple[np.ndarray, np.ndarray] | None = None

    def add(self, image: np.ndarray, truth: np.ndarray, eccentricity: np.ndarray) -> None:
        """Score one frame: linear RGB image and truth (h, w, 3), and each pixel's eccentricity in degrees."""
        a, b = to_space(image, self.space), to_space(truth, self.space)
        index = band_index(eccentricity)
        pixels = np.bincount(index, minlength=len(BANDS) + 1)
        _accumulate(self._pixels, pixels)
        _accumulate(self._sse, _band_sums(index, ((a - b) ** 2).sum(axis=2, dtype=np.float64)))
        _accumulate(self._ssim, _band_sums(index, ssim_map(a, b)))
        if self._previous is not None:
            flicker = np.abs((a - self._previous[0]) - (b - self._previous[1])).mean(axis=2)
            _accumulate(self._pairs, pixels)
            _accumulate(self._flicker, _band_sums(index, flicker))
        self._previous = (a, b)

    def result(self) -> dict[str, float | None]:
        """psnr_BAND (dB), ssim_BAND and flicker_BAND for each band and "image"; None where no pixel fell."""
        out: dict[str, float | None] = {}
        for name, n in self._pixels.items():
            mse = self._sse[name] / (3 * n) if n else None
            out[f"psnr_{name}"] = None if mse is None else math.inf if mse == 0 else 10 * math.log10(1.0 / mse)
            out[f"ssim_{name}"] = self._ssim[name] / n if n else None
        for name, n in self._pairs.items():
            out[f"flicker_{name}"] = self._flicker[name] / n if n else None
        return out


def _band_sums(index: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The sum of `values` (h, w) over each band's pixels (band_index), the pixels in no band last."""
    return np.bincount(index, weights=values.ravel(), minlength=len(BANDS) + 1)


def _accumulate(totals: dict[str, float], per_band: np.ndarray) -> None:
    """Add per-band sums (as _band_sums orders them) to totals by band name, and all of them to "image"."""
    for name, value in zip(BANDS, per_band, strict=False):
        totals[name] += value.item()
    totals["image"] += per_band.sum().item()
