"""The G-buffer: per traced sample, the attributes of its primary hit and of its first secondary hit.

These are the pixel attributes of kim2021 Table 1 (object id, normal, shadow count, texture existence,
at the primary and the secondary hit) plus depth and the reflect/refract weights that weier2016
(section 3.3) and the foveated methods need.
"""

from __future__ import annotations

from collections.abc import Collection
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
    def empty(cls, n: int, kept: Collection[str] | None = None) -> HitAttributes:
        """n samples' misses in the attributes named in `kept` (all by default); the others hold no samples, and
        the tracer stores nothing in them (store_block): a caller keeps what it reads."""
        kept = cls._fields if kept is None else kept
        unknown = set(kept) - set(cls._fields)
        if unknown:
            raise ValueError(f"no G-buffer attribute {sorted(unknown)}; they are {', '.join(cls._fields)}")
        size = {name: n if name in kept else 0 for name in cls._fields}
        return cls(
            np.full(size["depth"], np.inf, np.float32),
            np.zeros((size["normal_geometric"], 3), np.float32),
            np.zeros((size["normal_shading"], 3), np.float32),
            np.full(size["object_id"], -1, np.int32),
            np.zeros(size["shadow_count"], np.int16),
            np.zeros(size["textured"], bool),
            np.zeros(size["reflect"], np.float32),
            np.zeros(size["refract"], np.float32),
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


EVERY = np.zeros(0, bool)  # GBuffer.kept for every sample (writable like a caller's mask: one type for numba)


class GBuffer(NamedTuple):
    primary: HitAttributes
    secondary: HitAttributes  # the heavier of the reflected / refracted rays; a miss where none was spawned
    # (n,) bool: the samples whose attributes the tracer stores, besides the primary hit's depth, which it stores
    # for every sample; empty (EVERY): all of them. A method that reads the attributes of some pixels only
    # (kim21: its central region) skips the others' stores.
    kept: np.ndarray = EVERY

    @classmethod
    def empty(cls, n: int, primary: Collection[str] | None = None, secondary: Collection[str] | None = None) -> GBuffer:
        """n samples, each half keeping the attributes named (HitAttributes.empty: all by default)."""
        return cls(HitAttributes.empty(n, primary), HitAttributes.empty(n, secondary))

    def rows(self, n: int) -> GBuffer:
        """A view of the first n samples."""
        primary = HitAttributes(*(a[:n] for a in self.primary))
        secondary = HitAttributes(*(a[:n] for a in self.secondary))
        return GBuffer(primary, secondary, self.kept[:n] if len(self.kept) else self.kept)


class GBufferPool:
    """One G-buffer and one colour array kept across frames and grown when a frame needs more samples (to
    `most` at once where the caller knows a frame's bound), so that frames with varying sample counts do
    not allocate (and first-touch) fresh memory every time. Pages beyond what frames fill stay untouched.
    primary, secondary: the attributes each half keeps (GBuffer.empty); the primary hits' depth always."""

    def __init__(self, primary: Collection[str] | None = None, secondary: Collection[str] | None = None):
        self._kept = (None if primary is None else {"depth", *primary}, secondary)
        self._buffer = GBuffer.empty(0, *self._kept)
        self._color = np.empty((0, 3), np.float32)

    def rows(self, n: int, most: int = 0) -> tuple[GBuffer, np.ndarray]:
        """A G-buffer of n samples and their (n, 3) float32 colour, backed by the pooled arrays; the tracer
        writes every primary row and colour, and the secondary rows, if kept, start as misses."""
        if len(self._color) < n:
            size = max(n, most, int(1.25 * len(self._color)))
            self._buffer, self._color = GBuffer.empty(size, *self._kept), np.empty((size, 3), np.float32)
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
def holds_samples(attrs):
    """Whether a G-buffer half keeps any attribute (HitAttributes.empty's `kept`)."""
    depth, ng, ns, obj, shadow, tex, kr, kt = attrs
    sizes = depth.shape[0] + ng.shape[0] + ns.shape[0] + obj.shape[0]
    return sizes + shadow.shape[0] + tex.shape[0] + kr.shape[0] + kt.shape[0] > 0


@serial
def store_block(attrs, rows, kept, t, surf, textured, shadow_count, kr, kt, start, stop):
    """attrs[rows[i]] = attributes of hit i, for every i in [start, stop) with rows[i] >= 0, in the attributes
    that keep samples; besides the depth, only in the rows `kept` holds (GBuffer.kept; every row when empty)."""
    depth, a_ng, a_ns, a_obj, a_shadow, a_tex, a_kr, a_kt = attrs
    every = kept.shape[0] == 0
    hits, ng, ns, obj, material = surf.hit, surf.normal_geometric, surf.normal_shading, surf.object_id, surf.material
    k_depth, k_ng, k_ns, k_obj = depth.shape[0] > 0, a_ng.shape[0] > 0, a_ns.shape[0] > 0, a_obj.shape[0] > 0
    k_shadow, k_tex, k_kr, k_kt = a_shadow.shape[0] > 0, a_tex.shape[0] > 0, a_kr.shape[0] > 0, a_kt.shape[0] > 0
    for i in range(start, stop):
        i = np.uint64(i)  # unsigned indices: no negative-index wraparound on the loads and stores
        r = rows[i]
        if r < 0:
            continue
        r = np.uint64(r)
        hit = hits[i]
        if k_depth:
            depth[r] = t[i]
        if not (every or kept[r]):
            continue
        if k_obj:
            a_obj[r] = obj[i]
        for c in range(3):
            if k_ng:
                a_ng[r, c] = ng[i, c] if hit else 0.0
            if k_ns:
                a_ns[r, c] = ns[i, c] if hit else 0.0
        if k_shadow:
            a_shadow[r] = shadow_count[i] if hit else 0
        if k_tex:
            a_tex[r] = textured[np.uint64(material[i])] if hit else False
        if k_kr:
            a_kr[r] = kr[i] if hit else 0.0
        if k_kt:
            a_kt[r] = kt[i] if hit else 0.0
