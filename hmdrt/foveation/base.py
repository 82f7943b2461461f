"""What every rendering method receives and returns; methods are found by name in foveation.METHODS."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from hmdrt.optics.camera import EyeCamera
from hmdrt.telemetry.stats import FrameStats


@dataclass(frozen=True)
class FrameRequest:
    """One eye's frame: its camera, the gaze (unit, head frame), the frame number and the run's seed."""

    camera: EyeCamera
    gaze: np.ndarray
    frame: int = 0
    seed: int = 0


class Method(Protocol):
    name: str

    def render(self, request: FrameRequest, stats: FrameStats) -> np.ndarray:
        """Linear RGB image (height, width, 3) float32."""
        ...


def sample_keys(first_sample: int, count: int, seed: int) -> np.ndarray:
    """Random-stream keys of consecutive samples, distinct per seed."""
    return np.arange(first_sample, first_sample + count, dtype=np.int64) + (np.int64(seed) << np.int64(32))
