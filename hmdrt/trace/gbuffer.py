"""The G-buffer: per traced sample, the attributes of its primary hit and of its first secondary hit.

These are the pixel attributes of kim2021 Table 1 (object id, normal, shadow count, texture existence,
at the primary and the secondary hit) plus depth and the reflect/refract weights that weier2016
(section 3.3) and the foveated methods need.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from hmdrt.kernels.jit import serial


class HitAttributes(NamedTuple):
    depth: np.ndarray  # (n,) float32 hit distance along the ray; inf on a miss
    normal_geometric: np.ndarray  # (n, 3) float32, facing the ray; zero on a miss
    normal_shading: np.ndarray  # (n, 3) float32
    object_id: np.ndarray  # (n,) int32; -1 on a miss
    shadow_count: np.ndarray  # (n,) int16 shadow rays (point + area) that found an occluder
    textured: np.ndarray  # (n,) bool: the material has a texture
    reflect: np.ndarray  # (n,) float32 weight of the mirror ray
    refract: np.ndarray  # (n,) float32 weight of the refracted ray

    @classmethod
    def empty(cls, n: int) -> HitAttributes:
        return cls(
            np.full(n, np.inf, np.float32),
            np.zeros((n, 3), np.float32),
            np.zeros((n, 3), np.float32),
            np.full(n, -1, np.int32),
            np.zeros(n, np.int16),
            np.zeros(n, bool),
            np.zeros(n, np.float32),
            np.zeros(n, np.float32),
        )

    def clear(self) -> None:
        """Set every sample to a miss (for reused buffers)."""
        self.depth.fill(np.inf)
        self.object_id.fill(-1)
        for a in (
            self.normal_geometric,
            self.normal_shading,
            self.shadow_count,
            self.textured,
            self.reflect,
            self.refract,
        ):
            a.fill(0)


class GBuffer(NamedTuple):
    primary: HitAttributes
    secondary: HitAttributes  # the heavier of the reflected / refracted rays; a miss where none was spawned

    @classmethod
    def empty(cls, n: int) -> GBuffer:
        return cls(HitAttributes.empty(n), HitAttributes.empty(n))

    def rows(self, n: int) -> GBuffer:
        """A view of the first n samples."""
        return GBuffer(HitAttributes(*(a[:n] for a in self.primary)), HitAttributes(*(a[:n] for a in self.secondary)))


class GBufferPool:
    """One G-buffer and one colour array kept across frames and grown when a frame needs more samples (to
    `most` at once where the caller knows a frame's bound), so that frames with varying sample counts do
    not allocate (and first-touch) fresh memory every time. Pages beyond what frames fill stay untouched.
    secondary=False: a caller that reads the primary hits alone, whose G-buffers hold no secondary rows (the
    tracer then stores none, and nothing is cleared)."""

    def __init__(self, secondary: bool = True):
        self._secondary = secondary
        self._buffer = GBuffer.empty(0)
        self._color = np.empty((0, 3), np.float32)

    def rows(self, n: int, most: int = 0) -> tuple[GBuffer, np.ndarray]:
        """A G-buffer of n samples and their (n, 3) float32 colour, backed by the pooled arrays; the tracer
        writes every primary row and colour, and the secondary rows, if kept, start as misses."""
        if len(self._color) < n:
            size = max(n, most, int(1.25 * len(self._color)))
            primary = HitAttributes.empty(size)
            secondary = HitAttributes.empty(size if self._secondary else 0)
            self._buffer, self._color = GBuffer(primary, secondary), np.empty((size, 3), np.float32)
        view = self._buffer.rows(n)
        view.secondary.clear()
        return view, self._color[:n]


class LightBuffer(NamedTuple):
    """weier2016 section 3.1's light buffer: per sample, the irradiance of the stochastic sources (area
    lights, ambient occlusion) at the primary hit and the albedo it lands on; their product is the
    part of the sample's colour that those sources contribute (zero on a miss)."""

    irradiance: np.ndarray  # (n, 3) float32
    albedo: np.ndarray  # (n, 3) float32

    @classmethod
    def empty(cls, n: int) -> LightBuffer:
        return cls(np.zeros((n, 3), np.float32), np.zeros((n, 3), np.float32))


@serial
def store_block(attrs, rows, t, surf, textured, shadow_count, kr, kt, start, stop):
    """attrs[rows[i]] = attributes of hit i, for every i in [start, stop) with rows[i] >= 0."""
    depth, a_ng, a_ns, a_obj, a_shadow, a_tex, a_kr, a_kt = attrs
    hits, ng, ns, obj, material = surf.hit, surf.normal_geometric, surf.normal_shading, surf.object_id, surf.material
    for i in range(start, stop):
        r = rows[i]
        if r < 0:
            continue
        depth[r] = t[i]
        a_obj[r] = obj[i]
        hit = hits[i]
        for c in range(3):
            a_ng[r, c] = ng[i, c] if hit else 0.0
            a_ns[r, c] = ns[i, c] if hit else 0.0
        a_shadow[r] = shadow_count[i] if hit else 0
        a_tex[r] = textured[material[i]] if hit else False
        a_kr[r] = kr[i] if hit else 0.0
        a_kt[r] = kt[i] if hit else 0.0
