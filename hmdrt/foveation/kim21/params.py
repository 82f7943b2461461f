"""kim21's options (kim2021): the eccentricity bands of section 4.1, the samples per problematic subpixel of
section 4.6.2, tau_fov's shape (section 4.6.1, Figure 7), Table 1's thresholds (Figure 6's values), pixel reuse
(section 4.4) and temporal smoothing (section 4.7)."""

from __future__ import annotations

from typing import Annotated

import msgspec

from hmdrt.ranges import Deg

Positive = Annotated[float, msgspec.Meta(gt=0.0, le=1e3)]
Threshold = Annotated[float, msgspec.Meta(ge=0.0, le=10.0)]
Samples = Annotated[int, msgspec.Meta(ge=1, le=16)]
Weight = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]  # a blending factor: above 1, (1 - a)^i changes sign


class Kim21Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    # eccentricity bands (section 4.1)
    e_f: Deg = 3.3
    e_p: Deg = 5.5
    e_m: Deg = 12.1
    e_np: Deg = 30.0
    e_max: Deg = 45.0
    # samples per problematic subpixel by band (section 4.6.2)
    n_f: Samples = 9
    n_p: Samples = 4
    n_m: Samples = 2
    n_np: Samples = 1
    # tau_fov shape (tau_0, tau_f, tau_f', tau_np), Figure 7's tau^1
    tau_0: Positive = 1.0
    tau_f: Positive = 2.0
    tau_f_slope: Annotated[float, msgspec.Meta(ge=0.0, le=1e3)] = 0.5
    tau_np: Positive = 12.0
    # Table 1 thresholds, with Figure 6's values
    tau_col: Threshold = 0.02
    tau_poid: Threshold = 0.05
    tau_psn: Threshold = 0.06
    tau_psc: Threshold = 0.06
    tau_pte: Threshold = 0.02
    tau_soid: Threshold = 0.02
    tau_ssn: Threshold = 0.02
    tau_ssc: Threshold = 0.06
    tau_ste: Threshold = 0.02
    normal_cos: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)] = 0.95
    # the colour of a non-problematic subpixel: interpolated from the four surrounding pixel centres (kim2021,
    # Figure 2), or the pixel's own presampled colour as in Jin et al.'s selective supersampling
    interpolate: bool = True
    # pixel reuse (section 4.4) and temporal smoothing (section 4.7)
    reuse: bool = True
    n_reuse_max: Annotated[int, msgspec.Meta(ge=0, le=1000)] = 5
    tau_reuse: Threshold = 1.0
    reuse_px: Annotated[float, msgspec.Meta(ge=0.0, le=10.0)] = 0.2  # how far a reused colour may drift, pixels
    smooth: bool = True
    smooth_frames: Annotated[int, msgspec.Meta(ge=0, le=4)] = 4
    alpha: tuple[Weight, Weight, Weight, Weight, Weight, Weight] = (0.9, 0.8, 0.7, 0.5, 0.2, 0.1)
    depth_tolerance: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.02  # relative, for reuse and smoothing

    def __post_init__(self) -> None:
        if not self.e_f <= self.e_p <= self.e_m <= self.e_np <= self.e_max:
            raise ValueError("the bands need e_f <= e_p <= e_m <= e_np <= e_max")
