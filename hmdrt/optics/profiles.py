"""HMD display profiles: per-eye resolution, field of view, IPD and refresh rate.

Built-in profiles follow the headsets the papers used (DK2 in weier2016, FOVE 0 in weier2018) and
current ones. Field-of-view values are per eye, in the OpenXR XrFovf convention (left and down
negative, degrees); the right eye mirrors the left. Values marked approximate are public
measurements of the headset, not manufacturer specifications.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated

import msgspec

from hmdrt.errors import ConfigError
from hmdrt.files.configfile import parse_toml, read_limited
from hmdrt.ranges import MAX_EYE_PIXELS, refuse_large

Pixels = Annotated[int, msgspec.Meta(ge=1)]  # at most MAX_EYE_PIXELS per eye in all (HmdProfile.__post_init__)
HalfAngle = Annotated[float, msgspec.Meta(gt=-89.0, lt=89.0)]


class Fov(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Per-eye frustum half-angles in degrees (OpenXR XrFovf: left and down are negative)."""

    left: HalfAngle
    right: HalfAngle
    up: HalfAngle
    down: HalfAngle

    def __post_init__(self) -> None:
        if not (self.left < self.right and self.down < self.up):
            raise ValueError("fov needs left < right and down < up")

    @classmethod
    def symmetric(cls, horizontal_deg: float, vertical_deg: float) -> Fov:
        return cls(-horizontal_deg / 2, horizontal_deg / 2, vertical_deg / 2, -vertical_deg / 2)

    @classmethod
    def from_tangents(cls, left: float, right: float, up: float, down: float) -> Fov:
        deg = math.degrees
        return cls(-deg(math.atan(left)), deg(math.atan(right)), deg(math.atan(up)), -deg(math.atan(down)))

    def mirrored(self) -> Fov:
        return Fov(-self.right, -self.left, self.up, self.down)


class HmdProfile(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """One headset: per-eye pixels, left-eye FOV, inter-pupillary distance and refresh rate."""

    name: str
    width: Pixels
    height: Pixels
    fov: Fov
    refresh_hz: Annotated[float, msgspec.Meta(gt=0, le=1000)]
    ipd_mm: Annotated[float, msgspec.Meta(ge=0, le=100)] = 63.5

    def __post_init__(self) -> None:
        _check_pixels("width x height", self.width, self.height, ValueError)

    def eye_fov(self, eye: str) -> Fov:
        return self.fov if eye == "left" else self.fov.mirrored()

    @property
    def period_ns(self) -> int:
        return round(1e9 / self.refresh_hz)

    def with_resolution_text(self, text: str, name: str = "resolution") -> HmdProfile:
        """with_resolution from "WIDTHxHEIGHT" (a command-line or config value called `name`)."""
        try:
            w, h = (int(v) for v in text.lower().split("x"))
        except ValueError:
            raise ConfigError(f"{name} must be WIDTHxHEIGHT, e.g. 640x720, got {text!r}") from None
        return self.with_resolution(w, h, name)

    def with_resolution(self, width: int, height: int, name: str = "resolution") -> HmdProfile:
        """The same optics at another per-eye pixel count (given as `name`, which an error names)."""
        if width < 1 or height < 1:
            raise ConfigError(f"{name} must be at least 1x1 pixels, got {width}x{height}")
        _check_pixels(name, width, height)
        return msgspec.structs.replace(self, width=width, height=height)


def _check_pixels(name: str, width: int, height: int, error: type[Exception] = ConfigError) -> None:
    """Refuse a per-eye resolution past MAX_EYE_PIXELS before any buffer of it is made."""
    refuse_large(f"{name} {width}x{height} has", width * height, MAX_EYE_PIXELS, "pixels per eye", error)


PROFILES: dict[str, HmdProfile] = {
    p.name: p
    for p in (
        # Oculus SDK 0.4 default eye FOV tangents for DK2 (left eye): approximate.
        HmdProfile("dk2", 1182, 1464, Fov.from_tangents(1.0586, 1.0924, 1.3292, 1.3292), 75.0, 63.5),
        HmdProfile("rift_s", 1280, 1440, Fov.symmetric(90.0, 94.0), 80.0, 63.5),
        # FOVE 0: "up to 100 degrees" from the manufacturer, taken as the vertical extent: approximate.
        HmdProfile("fove0", 1280, 1440, Fov.symmetric(90.0, 100.0), 70.0, 64.0),
        # Vive Pro raw projection tangents as reported by OpenVR (left eye): approximate.
        HmdProfile("vive_pro_eye", 1440, 1600, Fov.from_tangents(1.3966, 1.2435, 1.4677, 1.4690), 90.0, 65.0),
        # Reduced resolutions with rift_s optics at 30 Hz: sim-cpu-640 (half of rift_s per side) is the compositor's
        # default display; sim-cpu, small enough for tests and quick runs on a 2-core CPU.
        HmdProfile("sim-cpu-640", 640, 720, Fov.symmetric(90.0, 94.0), 30.0, 63.5),
        HmdProfile("sim-cpu", 192, 216, Fov.symmetric(90.0, 94.0), 30.0, 63.5),
    )
}


def get_profile(name_or_path: str) -> HmdProfile:
    """A built-in profile by name, or one read from a TOML file with the HmdProfile fields."""
    if name_or_path in PROFILES:
        return PROFILES[name_or_path]
    path = Path(name_or_path)
    if path.suffix != ".toml":
        raise ConfigError(
            f"unknown profile {name_or_path!r}; built-in profiles: {', '.join(PROFILES)}, or a .toml file"
        )
    data = read_limited(path, "profile")
    try:
        return msgspec.convert(parse_toml(data), HmdProfile)
    except msgspec.ValidationError as exc:
        raise ConfigError(f"profile {path}: {exc}") from None
    except ValueError as exc:  # not UTF-8, not TOML, or nested too deeply
        raise ConfigError(f"profile {path} is not valid TOML: {exc}") from None
