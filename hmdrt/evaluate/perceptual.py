"""The optional perceptual score: FovVideoVDP (pyfvvdp, Mantiuk et al. 2021) in its foveated mode, which
takes the gaze point and so scores foveated output as the eye sees it. Installed with the `eval` extra
(pip install -e '.[eval]', CPU torch); results in JOD, 10 meaning no visible difference from the reference.

Each scored frame is one image pair (the metric's image mode) on a display with the profile's pixels and
horizontal field of view and the photometry of pyfvvdp's "standard_hmd"; a cell's JOD is their mean.
"""

from __future__ import annotations

import contextlib
import io

import numpy as np

from hmdrt.errors import ConfigError
from hmdrt.optics import HmdProfile
from hmdrt.present.encode import linear_to_srgb8


def require() -> None:
    """A ConfigError unless pyfvvdp and torch import."""
    try:
        import pyfvvdp  # noqa: F401
        import torch  # noqa: F401
    except ImportError as exc:
        raise ConfigError(f"jod = true needs the eval extra (pip install -e '.[eval]'): {exc}") from None


class JodScorer:
    def __init__(self, profile: HmdProfile, eye: str):
        require()
        import pyfvvdp
        import torch

        fov = profile.eye_fov(eye)
        geometry = pyfvvdp.fvvdp_display_geometry((profile.width, profile.height), fov_horizontal=fov.right - fov.left)
        with contextlib.redirect_stdout(io.StringIO()):  # it announces its settings
            self._metric = pyfvvdp.fvvdp(
                display_name="standard_hmd",
                display_geometry=geometry,
                foveated=True,
                quiet=True,
                device=torch.device("cpu"),
            )
        self._torch = torch

    def score(self, image: np.ndarray, reference: np.ndarray, gaze_xy: tuple[float, float]) -> float:
        """JOD of a linear RGB image against its reference, fixating pixel gaze_xy."""
        test, ref = (linear_to_srgb8(np.ascontiguousarray(a, dtype=np.float32)).astype(np.float32) / 255.0
                     for a in (image, reference))  # fmt: skip
        fixation = np.array([round(gaze_xy[0]), round(gaze_xy[1])])
        with self._torch.no_grad():
            jod, _ = self._metric.predict(test, ref, dim_order="HWC", fixation_point=fixation)
        return float(jod)
