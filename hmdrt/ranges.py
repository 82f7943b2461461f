"""The value ranges that configs, method options and bus messages share, checked by msgspec where strings and
bytes become typed values (TOML, query strings, msgpack): one definition each. And the size limits that refuse,
before any work starts, a resolution, a scene or an eval too large to fit; HMDRT_ALLOW_LARGE=1 lifts them."""

from __future__ import annotations

import os
from typing import Annotated

import msgspec

from hmdrt.errors import ConfigError

Deg = Annotated[float, msgspec.Meta(ge=0.0, le=180.0)]  # an angle from the gaze or a radius around it
Fraction = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]  # a probability, weight or reflectance
Finite = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]  # any coordinate or time: NaN and infinities refused

ALLOW_LARGE = "HMDRT_ALLOW_LARGE"  # set to 1 to lift the limits below on purpose
# 4096x4096 per eye: past the panels of current headsets (Varjo XR-4: 3840x3744 per eye); a frame of `full` takes
# about 43 bytes per pixel, so the limit is about 0.7 GB for one eye
MAX_EYE_PIXELS = 4096 * 4096
# building, packing and the tracer's BVH take 500-700 bytes per triangle at their peak (voxel_city, tunnel_geom):
# the limit is about 5-7 GB, ten times voxel_city?size=50 (1.03M), the largest the docs show
MAX_SCENE_TRIANGLES = 10_000_000
# frames an eval renders in all (groups.planned_frames): a day at 0.1 s per frame; the largest shipped config plans 11K
MAX_EVAL_FRAMES = 1_000_000


def large_allowed() -> bool:
    """Whether the user lifted the size limits on purpose (HMDRT_ALLOW_LARGE=1 in the environment)."""
    return os.environ.get(ALLOW_LARGE) == "1"


def refuse_large(what: str, amount: float, limit: int, unit: str, error: type[Exception] = ConfigError) -> None:
    """An `error` of one line when `amount` exceeds `limit` and the limits are not lifted: `what` names the key and
    its value ("resolution 20000x20000 has"), then the amount, the limit and how to lift it."""
    if amount > limit and not large_allowed():
        shown = f"{amount:,.0f}" if amount < 1e15 else f"{amount:.3g}" if amount < 1e300 else "over 1e300"
        raise error(
            f"{what} {shown} {unit}, more than the limit of {limit:,}; set {ALLOW_LARGE}=1 to allow it on purpose"
        )
