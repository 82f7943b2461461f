"""The optional perceptual score: FovVideoVDP (pyfvvdp, Mantiuk et al. 2021) in its foveated video mode, which
takes the gaze point of every frame and the frame rate, and so scores foveated output as the eye sees it over
time: a stale periphery, ghosting and reused pixels are temporal artefacts that single images do not show.
Installed with the `eval` extra (pip install -e '.[eval]', CPU torch); results in JOD, 10 meaning no visible
difference from the reference.

A cell's scored frames are one video on a display with the profile's pixels, horizontal field of view and
refresh rate and the photometry of pyfvvdp's "standard_hmd", the fixation following the gaze frame by frame.
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
        self._fps = float(profile.refresh_hz)

    def score(
        self, images: list[np.ndarray], references: list[np.ndarray], gaze_xy: list[tuple[float, float]]
    ) -> float:
        """JOD of a sequence of display-encoded frames (encode) against its reference frames, fixating pixel
        gaze_xy[k] in frame k, played at the profile's refresh rate."""
        test, ref = (np.stack(frames).astype(np.float32) / 255.0 for frames in (images, references))
        fixation = np.rint(np.asarray(gaze_xy, dtype=np.float64)).astype(np.int64)
        with self._torch.no_grad():
            jod, _ = self._metric.predict(
                test, ref, dim_order="FHWC", frames_per_second=self._fps, fixation_point=fixation
            )
        return float(jod)


def encode(image: np.ndarray) -> np.ndarray:
    """A linear RGB frame as the display shows it (8-bit sRGB): what JodScorer scores, kept at a quarter of the
    float frame's memory while a sequence is collected."""
    return linear_to_srgb8(np.ascontiguousarray(image, dtype=np.float32))
