"""Counter-based random numbers: a hash of (key, index, dimension), so results do not depend on
batching, threading or evaluation order (docs/architecture.md, Conventions: a seeded run reproduces bit for bit)."""

from hmdrt.kernels.jit import inline

_MASK = 0xFFFFFFFF


@inline
def hash32(a: int, b: int, c: int) -> int:
    """Mix three integers into 32 well-distributed bits (a lowbias32-style finaliser chain).

    All 64 bits of a count (keys carry the seed in their high half); b and c use their low 32 bits.
    """
    a = (a ^ (a >> 32)) & _MASK
    h = (a * 0x9E3779B1 + 0x7F4A7C15) & _MASK
    h ^= (b * 0x85EBCA77) & _MASK
    h = ((h ^ (h >> 16)) * 0x7FEB352D) & _MASK
    h ^= (c * 0xC2B2AE3D) & _MASK
    h = ((h ^ (h >> 15)) * 0x846CA68B) & _MASK
    return h ^ (h >> 16)


@inline
def uniform(a: int, b: int, c: int) -> float:
    """A float in [0, 1) determined by (a, b, c)."""
    return hash32(a, b, c) * (1.0 / 4294967296.0)
