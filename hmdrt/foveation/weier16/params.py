"""weier16's parameters (weier2016 sections 3.1-3.5), its support image's size (section 4.1) and the flags a pixel
carries through a frame."""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from hmdrt.foveation.stages.sampling import Foveal, foveal_config
from hmdrt.ranges import Deg, Fraction

DK2_SUPPORT = (256, 318, 1182, 1464)  # section 4.1: a 256 x 318 support image at 1182 x 1464
INFO = 3  # cache info per pixel: alpha, rho and the frame it was last touched
TRACED, FRESH, RESAMPLE, COVERED, FOVEA, SUPPORT, SHOWN = 1, 2, 4, 8, 16, 32, 64  # a pixel's flags: traced this
# frame; its sample replaces the cache (fovea or resampled); marked in the resampling info; covered by the
# reprojected mesh; inside r0; a pixel of the support image; covered, untraced and showing the support image's
# reconstruction (set by the cache update)


class Weier16Params(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    frc: Literal["small", "medium", "large", "full"] = "medium"
    r0: Deg | None = None
    r1: Deg | None = None
    p_min: Fraction | None = None
    support_w: Annotated[int, msgspec.Meta(ge=2, le=4096)] | None = None
    support_h: Annotated[int, msgspec.Meta(ge=2, le=4096)] | None = None
    eps_depth: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.05  # second difference of 1/z, relative
    eps_lum: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.2  # luminance contrast |a - b| / (a + b)
    eps_edge: Fraction = 0.1  # grazing angle: edge_t = max(n.d, 0) below this
    # full-resolution pixels the reprojection must move a cell (or a 4-neighbour) for its tests to run:
    # configs/eval/weier16_thresholds.toml
    eps_motion: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = 0.1
    eps_cache: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.05  # relative depth, cache vs new sample
    k_min: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.1
    k_max: Annotated[float, msgspec.Meta(gt=0.0, le=1.0)] = 0.5  # configs/eval/weier16_cache.toml
    t_max: Annotated[float, msgspec.Meta(ge=1.0, le=1e6)] = 30.0
    footprint_samples: Annotated[int, msgspec.Meta(ge=1, le=64)] = 4
    post: bool = True
    post_samples: Annotated[int, msgspec.Meta(ge=1, le=256)] = 8
    post_radius: Annotated[int, msgspec.Meta(ge=1, le=1024)] = 32  # pixels searched along each axis
    post_depth: Annotated[float, msgspec.Meta(gt=0.0, le=10.0)] = 0.02  # donor off the pixel's tangent plane
    post_normal: Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)] = 0.9  # least cosine between their normals

    def __post_init__(self) -> None:
        if self.k_min > self.k_max:
            raise ValueError("k_min must not exceed k_max")

    def foveal(self) -> Foveal:
        return foveal_config(self.frc, self.r0, self.r1, self.p_min)


def support_size(params: Weier16Params, width: int, height: int) -> tuple[int, int]:
    """The support image's size: as given, else 256 x 318 scaled from DK2's resolution to this one."""
    sw, sh, dw, dh = DK2_SUPPORT
    w = params.support_w or max(2, round(width * sw / dw))
    h = params.support_h or max(2, round(height * sh / dh))
    return min(w, width), min(h, height)
