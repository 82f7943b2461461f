"""Whitted tracing of camera samples as one fused kernel, run by each of the tracer's threads over the blocks of
samples it claims, each block a small wavefront over bounce depth that never leaves its thread's cache-sized scratch.

Per block and depth: generate the camera rays (depth 0), intersect them, build the shading records, make
the shadow / area / AO rays and trace them, shade, store the G-buffer and light buffer rows, then spawn
the reflected and refracted rays into the next level. Embree is called per ray from the kernel
(hmdrt.trace.embree), so nothing the size of the batch is allocated and no Python runs between the steps.
A sample's contributions add up in the order the former batch-wide wavefront added them (depth by depth,
parents in order, reflection before refraction), so the result does not depend on the block size.

Each thread owns a Lane of scratch sized for `capacity` rays per level; a level that needs more (deep
glass) takes fresh arrays for that block and reports the size it needed (meter.NEED), and the caller grows
the lanes for the next call.

The steps of a block are inlined in numba's IR (jit.inline), not compiled on their own: in each library numba
compiles, LLVM optimises and compiles again every function it calls, so steps of their own took a first run
6.5 s more CPU (28 s, not 21 s, for the tracer; bench/first_start.py).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from numba import typeof, types

from hmdrt.kernels.jit import inline, serial
from hmdrt.kernels.schedule import claim
from hmdrt.optics.camera import eye_direction
from hmdrt.trace import embree, meter
from hmdrt.trace.gbuffer import holds_samples, store_block
from hmdrt.trace.lighting import (
    RayBatch,
    _ao_rays,
    _area_rays,
    _point_rays,
    _shade_areas,
    _shade_finish,
    _shade_points,
    batch_empty,
    light_rays_block,
    shade_block,
)
from hmdrt.trace.secondary import Rays, interaction_block, rays_empty, spawn_block
from hmdrt.trace.surface import Surface, surface_block, surface_empty
from hmdrt.trace.tracer import Hits


class Work(NamedTuple):
    """A thread's scratch for one level of up to n rays (light batches: n x the rays per hit of each kind)."""

    hits: Hits
    surf: Surface
    point: RayBatch
    area: RayBatch
    ao: RayBatch
    acc: np.ndarray  # (n, 6) float64 shading sums (lighting.shade_block)
    local: np.ndarray  # (n, 3) float64 local radiance of each hit
    shadow_count: np.ndarray  # (n,) int16
    stochastic: np.ndarray  # (n, 3) float32
    kr: np.ndarray  # (n,) float32
    kt: np.ndarray  # (n,) float32
    counts: np.ndarray  # (n,) int64 children of each hit
    spawners: np.ndarray  # (n,) int64 the hits with children, in order
    first: np.ndarray  # (n,) int64 where its children go
    rows: np.ndarray  # (n,) int64 G-buffer row of each ray, -1 for none
    listed: np.ndarray  # (n,) int64 the level's rays in the order they are traced (_listed_rays)


class Lane(NamedTuple):
    """One thread's scratch: a level's work arrays, two ray buffers (this level, the next) and the block's
    radiance, Embree ray packet, clock and tally (meter)."""

    work: Work
    rays: Rays
    children: Rays
    radiance: np.ndarray  # (block, 3) float64
    packet: np.ndarray  # an Embree ray packet (embree.packets)
    clock: np.ndarray  # (2,) int64
    tally: np.ndarray  # (meter.TALLY,) int64


class Frame(NamedTuple):
    """What one trace_samples call reads and writes: samples (xy, keys) of an eye, the radiance out, and the
    G-buffer and light buffer, each written only where its flag is set (and the G-buffer in the attributes that keep
    samples)."""

    eye: object  # hmdrt.optics.camera.EyeRays
    xy: np.ndarray  # (n, 2) float32
    keys: np.ndarray  # (n,) int64
    out: np.ndarray  # (n, 3) float32
    gbuffer: object  # hmdrt.trace.gbuffer.GBuffer
    light: object  # hmdrt.trace.gbuffer.LightBuffer
    has_gbuffer: bool
    has_light: bool


class SceneArgs(NamedTuple):
    """The scene as the kernel sees it: Embree handle, packed arrays, light plan and recursion settings."""

    handle: int
    args: np.ndarray  # Embree query arguments (embree.coherent_args)
    geometry: object  # hmdrt.scene.pack.Geometry
    materials: object  # hmdrt.scene.pack.Materials
    lights: object  # hmdrt.scene.pack.Lights
    plan: object  # hmdrt.trace.lighting.LightPlan
    textured: np.ndarray  # (k,) bool per material
    max_depth: int
    secondary: bool


@serial
def work_empty(n, n_point, n_area, n_ao):
    return Work(
        Hits(np.empty(n, np.int32), np.empty(n, np.float32), np.empty(n, np.float32), np.empty(n, np.float32)),
        surface_empty(n),
        batch_empty(n * n_point),
        batch_empty(n * n_area),
        batch_empty(n * n_ao),
        np.empty((n, 6)),
        np.empty((n, 3)),
        np.empty(n, np.int16),
        np.empty((n, 3), np.float32),
        np.empty(n, np.float32),
        np.empty(n, np.float32),
        np.empty(n, np.int64),
        np.empty(n, np.int64),
        np.empty(n, np.int64),
        np.empty(n, np.int64),
        np.empty(n, np.int64),
    )


def lane_empty(capacity: int, block: int, n_point: int, n_area: int, n_ao: int) -> Lane:
    """A thread's scratch for levels of up to `capacity` rays and blocks of `block` samples."""
    return Lane(
        work_empty(capacity, n_point, n_area, n_ao),
        rays_empty(capacity),
        rays_empty(capacity),
        np.zeros((block, 3)),
        embree.packets(1)[0],
        np.zeros(2, np.int64),
        np.zeros(meter.TALLY, np.int64),
    )


@inline
def _occlude(scene, packet, batch, listed, hits, per_hit):
    """The occlusion rays of a level's hits, in the order its rays were traced (_listed_rays)."""
    o, d, far, occluded = batch
    return embree.occluded_rays(scene.handle, scene.args, packet, o, d, far, occluded, hits, per_hit, listed)


TILE_ROWS = 4  # pixel rows whose samples _tile_order interleaves
TILE_COLUMNS = embree.PACKET // TILE_ROWS  # so that a packet of dense samples spans 2 or 4 columns by 4 rows


@inline
def _band(xy, s):
    return int(xy[s, 1]) // TILE_ROWS


@inline
def _group(xy, s, stop):
    """The group of TILE_COLUMNS columns that sample s lies in, the largest int64 for s at `stop` (a run's end)."""
    return int(xy[s, 0]) // TILE_COLUMNS if s < stop else 0x7FFFFFFFFFFFFFFF


@inline
def _tile_order(xy, count, listed):
    """listed[:count]: samples 0 to count - 1 of xy in the order their camera rays are traced. Samples in scanline
    order come as runs of one pixel row each; up to TILE_ROWS runs in one band of rows are merged by group of
    TILE_COLUMNS columns (a stable merge, its first run first on a tie), so that a packet of neighbouring rays covers
    TILE_COLUMNS x 4 pixels, or the sparse samples of a few rows, not a row's: Embree's coherent packets trace such
    rays faster (docs/performance.md, "Rays in tiles"). Samples in any other order still give a permutation: each
    run keeps its order."""
    i = 0
    while i < count:
        band, row = _band(xy, i), int(xy[i, 1])
        c0, c1, c2, c3 = i, count, count, count  # each run's next sample; a run that does not exist is empty
        runs, j = 1, i + 1
        while j < count and _band(xy, j) == band:
            if int(xy[j, 1]) != row:
                if runs == TILE_ROWS:
                    break
                row, runs = int(xy[j, 1]), runs + 1
                if runs == 2:
                    c1 = j
                elif runs == 3:
                    c2 = j
                else:
                    c3 = j
            j += 1
        e0, e1, e2, e3 = min(c1, j), min(c2, j), min(c3, j), j
        k0, k1, k2, k3 = _group(xy, c0, e0), _group(xy, c1, e1), _group(xy, c2, e2), _group(xy, c3, e3)
        for out in range(i, j):
            if k0 <= k1 and k0 <= k2 and k0 <= k3:
                listed[out], c0 = c0, c0 + 1
                k0 = _group(xy, c0, e0)
            elif k1 <= k2 and k1 <= k3:
                listed[out], c1 = c1, c1 + 1
                k1 = _group(xy, c1, e1)
            elif k2 <= k3:
                listed[out], c2 = c2, c2 + 1
                k2 = _group(xy, c2, e2)
            else:
                listed[out], c3 = c3, c3 + 1
                k3 = _group(xy, c3, e3)
        i = j


@inline
def _listed_rays(frame, rays, listed, start, count, depth):
    """The order in which a level's rays are traced: the camera rays of samples [start, start + count) in tiles
    (_tile_order); below, the reflected rays, then the refracted ones, each kind in the order of the level (each is
    coherent on its own, a mix of the two is not)."""
    if depth == 0:
        _tile_order(frame.xy[start : start + count], count, listed)
        return
    n = 0
    for through in (False, True):
        for i in range(count):
            if rays.through[i] == through:
                listed[n] = i
                n += 1


@inline
def _raygen(frame, rays, radiance, start, count):
    """The camera rays of samples [start, start + count): their directions, then the fields every camera ray starts
    with, each in a loop of its own over flat views at unsigned indices, so that each vectorises."""
    eye, keys = frame.eye, frame.keys
    xy, directions = frame.xy.reshape(-1), rays.directions.reshape(-1)
    two, three = np.uint64(2), np.uint64(3)
    for i in range(count):
        s, e = two * np.uint64(start + i), three * np.uint64(i)
        dx, dy, dz = eye_direction(eye, xy[s], xy[s + np.uint64(1)])
        directions[e], directions[e + np.uint64(1)], directions[e + two] = dx, dy, dz
    ox, oy, oz = np.float32(eye.position[0]), np.float32(eye.position[1]), np.float32(eye.position[2])
    origins, throughput, summed = rays.origins.reshape(-1), rays.throughput.reshape(-1), radiance.reshape(-1)
    for i in range(count):
        e = three * np.uint64(i)
        origins[e], origins[e + np.uint64(1)], origins[e + two] = ox, oy, oz
    for e in range(3 * count):
        throughput[e], summed[e] = 1.0, 0.0
    for i in range(count):
        rays.owner[i], rays.key[i] = i, keys[start + i]
        rays.principal[i], rays.through[i] = True, False


@inline
def _accumulate(frame, w, rays, radiance, start, count, depth):
    """Add the level's local radiance to its samples; depth 0 also fills the light buffer."""
    local = w.local
    if depth == 0:
        for i in range(count):
            for c in range(3):
                radiance[i, c] += local[i, c]
        if frame.has_light:
            irradiance, albedo = frame.light
            hit, surf_albedo = w.surf.hit, w.surf.albedo
            for i in range(count):
                for c in range(3):
                    irradiance[start + i, c] = w.stochastic[i, c]
                    albedo[start + i, c] = surf_albedo[i, c] if hit[i] else 0.0
        return
    owner, thr = rays.owner, rays.throughput
    for i in range(count):
        o = np.uint64(owner[i])  # unsigned: no negative-index wraparound on the gather
        for c in range(3):
            radiance[o, c] += thr[i, c] * local[i, c]


@inline
def _store_gbuffer(frame, scene, w, rays, start, count, depth):
    rows = w.rows
    for i in range(count):
        rows[i] = start + rays.owner[i] if depth == 0 or rays.principal[i] else -1
    attrs = frame.gbuffer.primary if depth == 0 else frame.gbuffer.secondary
    store_block(attrs, rows, frame.gbuffer.kept, w.hits.t, w.surf, scene.textured, w.shadow_count, w.kr, w.kt, 0, count)


@inline
def _intersect(scene, packet, rays, hits, listed, count):
    """The level's rays to their first hits, in packets of consecutive rays of `listed` (_listed_rays)."""
    embree.intersect_rays(scene.handle, scene.args, packet, rays.origins, rays.directions, None, hits, 0, count, listed)


@inline
def _shade(scene, w, rays, count):
    shade_block(
        scene.lights,
        scene.plan,
        scene.materials,
        w.surf,
        rays.directions,
        w.point,
        w.area,
        w.ao,
        w.acc,
        w.local,
        w.shadow_count,
        w.stochastic,
        0,
        count,
    )


@inline
def _spawn(scene, w, rays, children, spawners, count, depth):
    """The next level's rays, the children of the level's first `spawners` hits in w.spawners, in a larger buffer
    than `children` where they do not fit, and how many there are. The camera rays' children go in the order their
    parents were traced (w.listed: tiles), deeper ones in their parents' order, so that each sample's rays keep
    theirs: its radiance adds up in the same order whatever the tiles."""
    if depth == 0:
        spawners = 0
        for r in range(count):
            i = w.listed[r]
            if w.counts[i]:
                w.spawners[spawners] = i
                spawners += 1
    total = 0
    for j in range(spawners):
        i = w.spawners[j]
        w.first[i] = total
        total += w.counts[i]
    if total > children.owner.shape[0]:
        children = rays_empty(total)
    spawn_block(scene.materials, w.surf, rays, w.kr, w.kt, w.first, depth + 1, children, w.spawners, spawners)
    return children, total


@inline
def _band_start(xy, s, reach):
    """Where block boundary s moves to: back to the start of its band of TILE_ROWS rows if that lies at most `reach`
    samples before it, so that _tile_order sees whole bands; else s."""
    if s >= xy.shape[0]:
        return s
    band = _band(xy, s)
    for back in range(s - 1, max(s - reach - 2, -1), -1):  # down to s - reach - 1: the sample before a band at reach
        if _band(xy, back) != band:
            return back + 1
    return 0 if s <= reach else s


@serial
def _trace_blocks(scene, frame, lane, block, counter):
    """One thread's share of a trace call: blocks of about `block` samples (their bounds moved back to the starts of
    bands of rows, by up to half a block: _band_start) claimed from `counter` until none is left; each block's
    samples [start, stop) traced, shaded and written. (The block's body is written here, not in an inlined helper:
    numba copies an inlined function's IR block by block, each copy with all its variables, 2.2 s of compiling.)"""
    n = frame.xy.shape[0]
    blocks = (n + block - 1) // block
    reach = block // 2
    b = claim(counter)
    while b < blocks:
        start = _band_start(frame.xy, b * block, reach)
        stop = _band_start(frame.xy, min(n, (b + 1) * block), reach)
        plan, tally, clock, packet, radiance = scene.plan, lane.tally, lane.clock, lane.packet, lane.radiance
        n_point, n_area, n_ao = scene.lights.point_position.shape[0], plan.area_total, plan.ao_samples
        t = meter.now(clock)
        rays, children = lane.rays, lane.children
        count = stop - start
        if count > rays.owner.shape[0]:
            rays = rays_empty(count)
        _raygen(frame, rays, radiance, start, count)
        t = meter.tick(tally, clock, meter.RAYGEN, t)
        for depth in range(scene.max_depth + 1):
            if count == 0:
                break
            tally[meter.NEED] = max(tally[meter.NEED], count)
            w = lane.work if count <= lane.work.kr.shape[0] else work_empty(count, n_point, n_area, n_ao)
            _listed_rays(frame, rays, w.listed, start, count, depth)
            _intersect(scene, packet, rays, w.hits, w.listed, count)
            kind = meter.PRIMARY if depth == 0 else meter.SECONDARY
            tally[meter.RAYS_PRIMARY if depth == 0 else meter.RAYS_SECONDARY] += count
            t = meter.tick(tally, clock, kind, t)
            surface_block(
                scene.geometry, scene.materials, rays.directions, w.hits.prim, w.hits.u, w.hits.v, w.surf, 0, count
            )
            t = meter.tick(tally, clock, meter.SURFACE, t)
            if n_point + n_area + n_ao:
                light_rays_block(scene.lights, plan, w.surf, rays.key, w.point, w.area, w.ao, 0, count)
                t = meter.tick(tally, clock, meter.LIGHTGEN, t)
            if n_point:
                tally[meter.RAYS_SHADOW] += _occlude(scene, packet, w.point, w.listed, count, n_point)
                t = meter.tick(tally, clock, meter.SHADOW, t)
            if n_area:
                tally[meter.RAYS_AREA] += _occlude(scene, packet, w.area, w.listed, count, n_area)
                t = meter.tick(tally, clock, meter.AREA, t)
            if n_ao:
                tally[meter.RAYS_AO] += _occlude(scene, packet, w.ao, w.listed, count, n_ao)
                t = meter.tick(tally, clock, meter.AO, t)
            _shade(scene, w, rays, count)
            _accumulate(frame, w, rays, radiance, start, count, depth)
            t = meter.tick(tally, clock, meter.SHADE, t)
            spawn = depth < scene.max_depth and scene.secondary
            store = frame.has_gbuffer and (depth == 0 or (depth == 1 and holds_samples(frame.gbuffer.secondary)))
            spawners = 0
            if spawn or store:
                spawners = interaction_block(
                    scene.materials, w.surf, rays, spawn, w.kr, w.kt, w.counts, w.spawners, 0, count
                )
                t = meter.tick(tally, clock, meter.SECONDARY if spawn else meter.GBUFFER, t)
            if store:
                _store_gbuffer(frame, scene, w, rays, start, count, depth)
                t = meter.tick(tally, clock, meter.GBUFFER, t)
            if not spawn:
                break
            next_rays, count = _spawn(scene, w, rays, children, spawners, count, depth)
            rays, children = next_rays, rays
            tally[meter.NEED] = max(tally[meter.NEED], count)
            t = meter.tick(tally, clock, meter.SECONDARY, t)
        out = frame.out
        for i in range(stop - start):
            for c in range(3):
                out[start + i, c] = radiance[i, c]
        meter.tick(tally, clock, meter.SHADE, t)
        b = claim(counter)


LITERAL_ZERO = types.literal(0)  # a 0 written at a call site types as itself, and the kernel compiles for that type


def _compile(kernel: Callable, *args: object) -> None:
    """Compiles `kernel` (or loads it from numba's cache) for these arguments' types, a numba type standing for its
    own (a literal or an omitted argument), without running it."""
    kernel.compile(tuple(a if isinstance(a, types.Type) else typeof(a) for a in args))


def compile_part(scene: SceneArgs, lane: Lane, gbuffer: object, part: int) -> None:
    """Compiles into numba's cache (or loads from it) the kernels that the steps of a block call, those of a level's
    first steps (part 0: intersection, surfaces, light rays and G-buffer rows, about 6 s of a first run's CPU) or of
    its last ones (part 1: occlusion, shading, interactions and spawning, about 6.5 s), each with the argument types
    _trace_blocks calls it with, here from the scene's arguments, a lane's scratch and a G-buffer. Two processes
    compile the two parts side by side on a first run, and the tracer's kernel then loads both
    (hmdrt.trace.compile_aside): calling them from a kernel of its own would have LLVM compile them again in it. A call
    site's types that differ from these leave that kernel to the tracer's compile; tests/test_compile_aside.py checks
    that none does."""
    w, rays, count, zero = lane.work, lane.rays, 0, LITERAL_ZERO
    lights, plan, mats, surf = scene.lights, scene.plan, scene.materials, w.surf
    embree_args = (scene.handle, scene.args, lane.packet)
    if part == 0:
        o, d, hits = rays.origins, rays.directions, w.hits
        _compile(embree.intersect_rays, *embree_args, o, d, None, hits, zero, count, w.listed)
        _compile(surface_block, scene.geometry, mats, d, hits.prim, hits.u, hits.v, surf, zero, count)
        _compile(_point_rays, lights, surf, w.point, zero, count)
        _compile(_area_rays, lights, plan, surf, rays.key, w.area, zero, count)
        _compile(_ao_rays, plan, surf, rays.key, w.ao, zero, count)
        attrs = (gbuffer.primary, w.rows, gbuffer.kept, hits.t, surf, scene.textured, w.shadow_count, w.kr, w.kt)
        _compile(store_block, *attrs, zero, count)
        _compile(holds_samples, gbuffer.secondary)
    elif part == 1:
        o, d, far, occluded = w.point
        _compile(embree.occluded_rays, *embree_args, o, d, far, occluded, count, count, w.listed)
        shading = (mats, surf, rays.directions)
        shaded = (w.acc, w.local, w.stochastic, w.shadow_count)
        _compile(_shade_points, lights, plan, *shading, w.point, w.ao, shaded, True, zero, count)
        _compile(_shade_areas, lights, plan, *shading, w.area, w.acc, w.shadow_count, zero, count)
        _compile(_shade_finish, plan, mats, surf, w.ao, w.acc, w.local, w.stochastic, zero, count)
        weights = (w.kr, w.kt)
        _compile(interaction_block, mats, surf, rays, True, *weights, w.counts, w.spawners, zero, count)
        _compile(spawn_block, mats, surf, rays, *weights, w.first, 1, lane.children, w.spawners, count)
        _compile(rays_empty, zero)  # typing meets _spawn's total at its first value, 0, on the way to int64
    else:
        raise ValueError(f"part {part} of the tracer's kernels: there are two, 0 and 1")


def trace(
    scene: SceneArgs, frame: Frame, lanes: list[Lane], block: int, share: Callable[[Callable[[int], None]], None]
) -> None:
    """Radiance of every sample of `frame` into frame.out, in blocks of `block` samples that the threads of `share`
    (hmdrt.trace.tracer.Tracer.share) claim as each frees up, thread t on lanes[t].

    A serial kernel on each thread, not one parallel kernel: numba builds a parallel kernel's body into four
    nested libraries, and LLVM optimises and compiles the whole tracer again in each (on a first run, 8.5 s more
    CPU with the steps of their own, 11 s more with them inlined)."""
    counter = np.zeros(1, np.int64)
    share(lambda t: _trace_blocks(scene, frame, lanes[t], block, counter))
