"""HMD optics: display profiles, per-eye cameras and eccentricity maps."""

from hmdrt.optics.camera import EyeCamera, pixel_centres
from hmdrt.optics.profiles import PROFILES, Fov, HmdProfile, get_profile

__all__ = ["PROFILES", "EyeCamera", "pixel_centres", "Fov", "HmdProfile", "get_profile"]
