"""What a head tracker reports of the true head pose: a model of its published precision and rate, the head's
counterpart of the eye tracker model (hmdrt.tracking.model), whose sampling and noise scale it shares.

- Position noise (position_mm): the RMS distance between successive reported positions of a still head (RMS
  sample to sample, RMS-S2S), white noise of standard deviation position_mm / sqrt(6) on each of three axes.
- Orientation noise (orientation_deg): the RMS angle between successive reported orientations of a still head,
  each sample turned by a white rotation vector of standard deviation orientation_deg / sqrt(6) on each axis
  (for small angles the rotation between two samples is the difference of their rotation vectors).
  RMS-S2S rather than the RMS of a white jitter about the true pose, so that a head tracker's precision means
  what an eye tracker's does (Holmqvist, Nystrom & Mulvey 2012, "Eye tracker data quality", ETRA). For white
  noise the two differ by a fixed factor: RMS-S2S is sqrt(2) times the RMS jitter about the true pose.
- Sampling rate (rate_hz): samples at multiples of the period, each the true pose then (sample and hold).

Left out: a fixed offset (the virtual
world lives in the tracker's frame, so an offset such as the tilted ground plane Niehorster et al. 2017 found,
below, moves the whole world, not the view of it), drift (the optical trackers modelled correct their IMU
continuously over a trace of seconds), and tracking loss (kept simple: each preset reports every sample).

A true head pose is a PoseSequence; PoseTracker.report turns it into the reported one, deterministically for a
seed.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

import msgspec
import numpy as np

from hmdrt.spatial import quat_from_rotvec, quat_multiply
from hmdrt.tracking.model import Sampling, preset_named, sampling_rate_hz, white_noise


@dataclass(frozen=True)
class PoseSequence:
    """Timestamped head poses: t_ns (n,) int64 rising, position (n, 3) metres and orientation (n, 4) unit
    quaternions (w, x, y, z) in the world, valid (n,) bool (an invalid sample's pose means nothing)."""

    t_ns: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    valid: np.ndarray

    @property
    def rate_hz(self) -> float | None:
        """The sequence's sampling rate (sampling_rate_hz)."""
        return sampling_rate_hz(self.t_ns)


class PoseTracker(msgspec.Struct, Sampling, frozen=True, forbid_unknown_fields=True):
    """A head tracker's errors. The defaults are a perfect tracker: no noise, every true sample reported."""

    position_mm: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = 0.0  # RMS sample to sample
    orientation_deg: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.0  # RMS sample to sample
    rate_hz: Annotated[float, msgspec.Meta(ge=1.0)] = math.inf  # inf: every true sample

    def report(self, truth: PoseSequence, seed: int | Sequence[int] = 0) -> PoseSequence:
        """What the tracker reports of `truth` (ValueError where it samples faster than truth): its samples from
        the first multiple of its period at or after truth's first sample to its last, each noisy, invalid where
        truth is. Without noise each reported pose is the true one exactly. The same seed gives the same samples."""
        t, pick = self.sample(truth.t_ns, "the true head pose")
        rng = np.random.default_rng(seed)
        position, orientation = truth.position[pick], truth.orientation[pick]
        if self.position_mm > 0.0:
            position = position + white_noise(rng, self.position_mm * 1e-3, (len(t), 3))
        if self.orientation_deg > 0.0:
            turns = white_noise(rng, math.radians(self.orientation_deg), (len(t), 3))
            orientation = np.array(
                [quat_multiply(quat_from_rotvec(v), q) for v, q in zip(turns, orientation, strict=True)]
            )
        return PoseSequence(t, position, orientation, truth.valid[pick])


# Each figure with its source. Niehorster, Li & Lappe 2017 ("The accuracy and precision of position and
# orientation tracking in the HTC Vive virtual reality system for scientific research", i-Perception 8(3)) measured
# the HTC Vive's headset with Lighthouse tracking: sub-millimetre precision and an orientation precision of about
# 0.01-0.02 deg while tracking is stable. No maker publishes these figures; an inside-out headset (Rift S, Quest)
# needs a measured precision before it is a preset (Monica & Aleotti 2022, Virtual Reality 26, measured the Rift
# S's tracking against motion capture).
PRESETS: dict[str, PoseTracker] = {
    "perfect": PoseTracker(),
    # Niehorster et al. 2017: 0.02 deg, the upper end of their orientation precision; 0.3 mm for their
    # "sub-millimetre" (Kreylos 2016, doc-ok.org "Lighthouse tracking examined", about 0.3 mm RMS with both base
    # stations in view: not re-read here); 90 Hz, once per frame of the Vive's display, as an application reads it
    "htc-vive": PoseTracker(position_mm=0.3, orientation_deg=0.02, rate_hz=90.0),
}


def pose_tracker_named(name: str) -> PoseTracker:
    """The preset of that name; ValueError naming the presets for another."""
    return preset_named(PRESETS, name, "pose_tracker", PoseTracker)
