"""Embree 4 called directly from numba: the library embreex ships, one scene per Geometry, and the
intersect / occluded calls that the tracing kernels make inside their own parallel loops.

embreex's run() allocates its result arrays on every call and needs a Python thread pool to use more than
one core; calling Embree from numba removes both. The scene is built exactly as embreex builds it (default
device, robust scene, one triangle geometry with 16-byte vertex stride), so the hits are the same
(tests/test_tracer.py compares them ray by ray).

Rays go to Embree in packets of PACKET (RTCRayHit8 or RTCRayHit16 of rtcore_ray.h: RTCRayHit's fields as arrays
of 8 or 16, in a float32 array per thread) with the coherent flag, which traverses the BVH once for the whole
packet: primary and shadow rays of neighbouring pixels trace about 2x faster than one by one (rtcIntersect1), with
the same hits. PACKET is 16 where Embree traces such packets natively (AVX-512), else 8 (an rtcIntersect16 there
traces its rays one by one); numba's cache keeps each CPU's code apart, so each machine compiles its own.
The kernels take a packet's views and rays' coordinates apart once per batch, not per ray: each array view numba
makes costs reference counting.
"""

from __future__ import annotations

import ctypes
import glob
import os
from typing import NamedTuple

import embreex
import llvmlite.binding as llvm
import numpy as np
from numba import types

from hmdrt.kernels.jit import inline, serial

# RTCRayHit's fields in order: ray org/tnear 0-3, dir/time 4-7, tfar 8, mask 9, id 10, flags 11; hit Ng 12-14,
# u 15, v 16, primID 17, geomID 18, instID 19, instPrimID 20 (where Embree was built with instance arrays)
_TFAR, _MASK, _ID, _FLAGS, _U, _V, _PRIM, _GEOM, _INST = 8, 9, 10, 11, 15, 16, 17, 18, 19
INVALID_ID = 0xFFFFFFFF
MISS_T = 1e37  # tfar of a ray that may hit anything (as embreex)

ARGS_WORDS = 16  # uint32 words holding an RTCIntersectArguments / RTCOccludedArguments
_COHERENT, _ALL_FEATURES = 1 << 16, 0xFFFFFFFF  # RTC_RAY_QUERY_FLAG_COHERENT, RTC_FEATURE_FLAG_ALL

_GEOMETRY_TRIANGLE, _BUFFER_INDEX, _BUFFER_VERTEX = 0, 0, 1
_FORMAT_UINT3, _FORMAT_FLOAT3 = 0x5003, 0x9003
_SCENE_FLAG_ROBUST = 1 << 2


def _library_path() -> str:
    """libembree4 as shipped inside the embreex wheel (embreex.libs on Linux, .dylibs on macOS)."""
    package = os.path.dirname(embreex.__file__)
    patterns = ("*embree4*.so*", "*embree4*.dylib", "embree4*.dll")
    for folder in (os.path.join(package, "..", "embreex.libs"), os.path.join(package, ".dylibs"), package):
        for pattern in patterns:
            found = sorted(glob.glob(os.path.join(folder, pattern)))
            if found:
                return os.path.realpath(found[0])
    raise ImportError(f"no Embree 4 library found in the embreex package at {package}")


_PATH = _library_path()
llvm.load_library_permanently(_PATH)  # numba links rtcIntersectN / rtcOccludedN against it, also from its cache
_lib = ctypes.CDLL(_PATH)
_P = ctypes.c_void_p
for _name, _res, _args in (
    ("rtcNewDevice", _P, [ctypes.c_char_p]),
    ("rtcReleaseDevice", None, [_P]),
    ("rtcGetDeviceError", ctypes.c_int, [_P]),
    ("rtcGetDeviceProperty", ctypes.c_ssize_t, [_P, ctypes.c_int]),
    ("rtcNewScene", _P, [_P]),
    ("rtcSetSceneFlags", None, [_P, ctypes.c_int]),
    ("rtcCommitScene", None, [_P]),
    ("rtcReleaseScene", None, [_P]),
    ("rtcNewGeometry", _P, [_P, ctypes.c_int]),
    ("rtcSetNewGeometryBuffer", _P, [_P, ctypes.c_int, ctypes.c_uint, ctypes.c_int, ctypes.c_size_t, ctypes.c_size_t]),
    ("rtcCommitGeometry", None, [_P]),
    ("rtcAttachGeometry", ctypes.c_uint, [_P, _P]),
    ("rtcReleaseGeometry", None, [_P]),
):
    _fn = getattr(_lib, _name)
    _fn.restype, _fn.argtypes = _res, _args

_NATIVE_RAY16 = 34  # RTC_DEVICE_PROPERTY_NATIVE_RAY16_SUPPORTED


def native_packet() -> int:
    """Rays per packet: 16 where this CPU's Embree traces RTCRayHit16 packets natively, else 8."""
    device = _lib.rtcNewDevice(None)
    if not device:
        raise RuntimeError("Embree could not create a device")
    try:
        return 16 if _lib.rtcGetDeviceProperty(device, _NATIVE_RAY16) else 8
    finally:
        _lib.rtcReleaseDevice(device)


PACKET = native_packet()
PACKET_WORDS = 24 * PACKET  # float32 words of a packet (RTCRayHitN with room for instPrimID), then its valid mask

# pointers travel as integers: the same registers on every 64-bit ABI Embree supports
_sig = types.void(types.intp, types.intp, types.intp, types.intp)
_rtc_intersect = types.ExternalFunction(f"rtcIntersect{PACKET}", _sig)
_rtc_occluded = types.ExternalFunction(f"rtcOccluded{PACKET}", _sig)


class EmbreeScene:
    """A committed Embree scene of one triangle mesh; `handle` is what the kernels pass to intersect / occluded."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        self._device = _lib.rtcNewDevice(None)
        if not self._device:
            raise RuntimeError("Embree could not create a device")
        self._scene = _lib.rtcNewScene(self._device)
        _lib.rtcSetSceneFlags(self._scene, _SCENE_FLAG_ROBUST)
        if len(faces):
            geom = _lib.rtcNewGeometry(self._device, _GEOMETRY_TRIANGLE)
            vbuf = _lib.rtcSetNewGeometryBuffer(geom, _BUFFER_VERTEX, 0, _FORMAT_FLOAT3, 16, len(vertices))
            ibuf = _lib.rtcSetNewGeometryBuffer(geom, _BUFFER_INDEX, 0, _FORMAT_UINT3, 12, len(faces))
            if vbuf and ibuf:
                v = np.ctypeslib.as_array(ctypes.cast(vbuf, ctypes.POINTER(ctypes.c_float)), (len(vertices), 4))
                v[:, :3] = vertices
                f = np.ctypeslib.as_array(ctypes.cast(ibuf, ctypes.POINTER(ctypes.c_uint32)), (len(faces), 3))
                f[:] = faces
                _lib.rtcCommitGeometry(geom)
                _lib.rtcAttachGeometry(self._scene, geom)
            _lib.rtcReleaseGeometry(geom)
        _lib.rtcCommitScene(self._scene)
        error = _lib.rtcGetDeviceError(self._device)
        if error:
            self.close()
            raise RuntimeError(f"Embree could not build the scene (RTCError {error})")
        self.handle = int(self._scene)

    def close(self) -> None:
        """Release the scene and device; kernels must not use `handle` afterwards."""
        if self._scene:
            _lib.rtcReleaseScene(self._scene)
            self._scene = None
        if self._device:
            _lib.rtcReleaseDevice(self._device)
            self._device = None
        self.handle = 0


def _aligned(count: int, words: int, dtype=np.float32) -> np.ndarray:
    """count rows of `words` 4-byte words, each row 64-byte aligned (one per thread: no false sharing)."""
    per = -(-words // 16) * 16
    raw = np.zeros(count * per + 16, dtype)
    skip = (-raw.ctypes.data % 64) // 4
    return raw[skip : skip + count * per].reshape(count, per)


def packets(count: int) -> np.ndarray:
    """count float32 packets: PACKET_WORDS of rays, then PACKET int32 words of valid mask."""
    return _aligned(count, PACKET_WORDS + PACKET)


def coherent_args() -> np.ndarray:
    """Intersect / occluded arguments asking Embree to treat a packet's rays as coherent."""
    args = _aligned(1, ARGS_WORDS, np.uint32)[0]
    args[0], args[1] = _COHERENT, _ALL_FEATURES  # flags, feature_mask; context, filter, callback NULL
    return args


class Packet(NamedTuple):
    """A packet as the helpers fill and read it: its words as float32 (origins, directions, distances) and as
    uint32 (masks, ids, hits), and the valid mask after them; taken apart once per batch (packet_views)."""

    rays: np.ndarray  # (PACKET_WORDS,) float32
    words: np.ndarray  # (PACKET_WORDS,) uint32, the same memory
    valid: np.ndarray  # (PACKET,) int32


@inline
def packet_views(packet):
    """The Packet over one row of packets()."""
    rays = packet[:PACKET_WORDS]
    return Packet(rays, rays.view(np.uint32), packet[PACKET_WORDS : PACKET_WORDS + PACKET].view(np.int32))


@inline
def set_lane(p, k, ox, oy, oz, dx, dy, dz, tfar, ident):
    """Ray k of Packet p (words field * PACKET + k), with no hit yet; ident: the caller's, kept (lane_id)."""
    rays, words = p.rays, p.words
    rays[k], rays[PACKET + k], rays[2 * PACKET + k], rays[3 * PACKET + k] = ox, oy, oz, 0.0
    rays[4 * PACKET + k], rays[5 * PACKET + k], rays[6 * PACKET + k] = dx, dy, dz
    rays[7 * PACKET + k] = 0.0
    rays[_TFAR * PACKET + k] = tfar
    words[_MASK * PACKET + k] = INVALID_ID
    words[_ID * PACKET + k] = ident
    words[_FLAGS * PACKET + k] = 0
    words[_PRIM * PACKET + k] = words[_GEOM * PACKET + k] = words[_INST * PACKET + k] = INVALID_ID


@inline
def _valid(p, lanes):
    valid = p.valid
    for k in range(PACKET):
        valid[k] = -1 if k < lanes else 0
    return valid


@inline
def intersect_packet(scene, p, lanes, args):
    """Trace the first `lanes` rays of Packet p (set_lane) to their first hits (lane_hit)."""
    _rtc_intersect(_valid(p, lanes).ctypes.data, scene, p.rays.ctypes.data, args.ctypes.data)


@inline
def occluded_packet(scene, p, lanes, args):
    """Trace the first `lanes` rays of Packet p (set_lane) for occluders (lane_occluded)."""
    _rtc_occluded(_valid(p, lanes).ctypes.data, scene, p.rays.ctypes.data, args.ctypes.data)


@inline
def lane_hit(p, k):
    """(prim, t, u, v) of ray k of a traced Packet, as intersect() returns them."""
    prim = p.words[_PRIM * PACKET + k]
    if prim == INVALID_ID:
        return -1, np.float32(np.inf), np.float32(0.0), np.float32(0.0)
    return np.int32(prim), p.rays[_TFAR * PACKET + k], p.rays[_U * PACKET + k], p.rays[_V * PACKET + k]


@inline
def lane_occluded(p, k):
    return p.rays[_TFAR * PACKET + k] < 0.0


@inline
def lane_id(p, k):
    return p.words[_ID * PACKET + k]


@inline
def _listed(listed, r):
    """The r-th ray of a trace: r itself, or listed[r] where the caller lists the rays in the order to trace them."""
    return r if listed is None else listed[r]


@serial
def intersect_rays(scene, args, packet, origins, directions, far, hits, start, stop, listed=None):
    """hits[i] = first hit of ray i within (0, far[i]] (far None: MISS_T), for the rays i at [start, stop) of
    `listed` (None: the rays [start, stop) themselves), in packets of consecutive ones."""
    prim, t, u, v = hits
    p, o, d = packet_views(packet), origins, directions
    for s in range(start, stop, PACKET):
        lanes = min(PACKET, stop - s)
        for k in range(lanes):
            i = _listed(listed, s + k)
            tfar = MISS_T if far is None else far[i]
            set_lane(p, k, o[i, 0], o[i, 1], o[i, 2], d[i, 0], d[i, 1], d[i, 2], tfar, 0)
        intersect_packet(scene, p, lanes, args)
        for k in range(lanes):
            i = _listed(listed, s + k)
            prim[i], t[i], u[i], v[i] = lane_hit(p, k)


@serial
def occluded_rays(scene, args, packet, origins, directions, far, occluded, rows, columns, listed=None):
    """occluded[j] = whether anything lies along ray j within (0, far[j]], for the rows x columns rays
    j = row * columns + column, of the first `rows` rows of `listed` (None: rows 0 to rows - 1). Rays with far <= 0
    are not traced (False); the others go in packets column by column, so that a packet holds the same light sample
    of neighbouring hits. Returns how many were traced."""
    p, o, d = packet_views(packet), origins, directions
    traced = lanes = 0
    for column in range(columns):
        for r in range(rows):
            j = _listed(listed, r) * columns + column
            if far[j] <= 0.0:
                occluded[j] = False
                continue
            set_lane(p, lanes, o[j, 0], o[j, 1], o[j, 2], d[j, 0], d[j, 1], d[j, 2], far[j], j)
            lanes += 1
            if lanes == PACKET:
                traced += _flush_occluded(scene, args, p, lanes, occluded)
                lanes = 0
    return traced + _flush_occluded(scene, args, p, lanes, occluded)


@inline
def _flush_occluded(scene, args, p, lanes, occluded):
    if lanes:
        occluded_packet(scene, p, lanes, args)
        for k in range(lanes):
            occluded[lane_id(p, k)] = lane_occluded(p, k)
    return lanes
