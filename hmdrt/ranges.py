"""The value ranges that configs, method options and bus messages share, checked by msgspec where strings and
bytes become typed values (TOML, query strings, msgpack): one definition each."""

from __future__ import annotations

from typing import Annotated

import msgspec

Deg = Annotated[float, msgspec.Meta(ge=0.0, le=180.0)]  # an angle from the gaze or a radius around it
Fraction = Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]  # a probability, weight or reflectance
Finite = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]  # any coordinate or time: NaN and infinities refused
