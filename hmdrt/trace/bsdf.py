"""Whitted surface interaction: mirror reflection, Snell refraction with total internal reflection,
the exact unpolarised dielectric Fresnel term, and the energy split between reflected and transmitted rays.

Vectors are passed as scalar triples so the numba kernels inline these without allocating.
"""

import math

from hmdrt.kernels.jit import inline


@inline
def reflect(dx, dy, dz, nx, ny, nz):
    """Mirror direction of d about unit normal n."""
    k = 2.0 * (dx * nx + dy * ny + dz * nz)
    return dx - k * nx, dy - k * ny, dz - k * nz


@inline
def refract(dx, dy, dz, nx, ny, nz, eta):
    """Snell refraction of unit d through unit n facing against d (n.d < 0), eta = n_incident / n_transmitted.

    Returns (ok, tx, ty, tz); ok is False on total internal reflection.
    """
    cos_i = -(dx * nx + dy * ny + dz * nz)
    sin2_t = eta * eta * max(0.0, 1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        return False, 0.0, 0.0, 0.0
    cos_t = math.sqrt(1.0 - sin2_t)
    k = eta * cos_i - cos_t
    return True, eta * dx + k * nx, eta * dy + k * ny, eta * dz + k * nz


@inline
def fresnel_dielectric(cos_i, eta):
    """Unpolarised Fresnel reflectance at a dielectric interface; 1 under total internal reflection."""
    cos_i = min(max(cos_i, 0.0), 1.0)
    sin2_t = eta * eta * (1.0 - cos_i * cos_i)
    if sin2_t >= 1.0:
        return 1.0
    cos_t = math.sqrt(1.0 - sin2_t)
    rs = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    rp = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    return 0.5 * (rs * rs + rp * rp)


@inline
def split(reflectance, transmittance, cos_i, eta):
    """Weights (k_reflect, k_transmit) of the mirror and refracted rays; they sum to reflectance + transmittance.

    The transmitted share is divided by the Fresnel term; under total internal reflection all of it reflects.
    """
    if transmittance <= 0.0:
        return reflectance, 0.0
    f = fresnel_dielectric(cos_i, eta)
    return reflectance + transmittance * f, transmittance * (1.0 - f)
