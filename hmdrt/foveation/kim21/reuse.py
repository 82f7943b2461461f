"""kim21's pixel reusability test (kim2021 section 4.4): each central pixel presampled (section 4.3) is
back-projected into the previous frame and copies that frame's rendered colour where it meets the same surface and
the two colour reference attributes pass section 3's two-step disparity test (Table 1's geometry attributes at the
primary and the secondary hit select tau_sel, then Mitchell's contrast at tau_sel x tau_reuse), at most
n_reuse_max times in a row."""

from __future__ import annotations

import math
from typing import NamedTuple

import numba as nb
import numpy as np

from hmdrt.foveation.kim21.disparity import _discordant_threshold, _dot, _geometry, _pair_contrast_fails, _rgb, _taus
from hmdrt.foveation.stages.temporal import eye_point, view_project
from hmdrt.kernels.jit import kernel, serial
from hmdrt.kernels.schedule import claim
from hmdrt.optics.projection import FAR, nearest_index


class Kept(NamedTuple):
    """A frame's buffers that the next frame reads: presampled colour, hit distance, reuse count, rendered colour,
    and what the rendered colour is worth to a later reuse: its class and where it was sampled."""

    ref: np.ndarray  # (n, 3) float32 the presampled colour at the pixel centres, where the tests read it: the
    # central pixels and their neighbours (Foveation.table1)
    depth: np.ndarray  # (n,) float32 the history's depth slot: distance of the first hit, inf on a miss
    flags: np.ndarray  # (n,) int32 times in a row the pixel was reused; 0 where rendered; central pixels only
    rendered: np.ndarray  # (n, 3) float32 the history's colour slot, before smoothing: the presampled colour, which
    # the tracer writes, then the reused or the resolved one
    level: np.ndarray  # (n,) uint8 samples per problematic subpixel the colour was rendered with; 0 outside e_np
    drift: np.ndarray  # (n, 2) float32 where the colour was rendered, in pixels from the pixel centre; central only
    # (flags and drift of a pixel outside e_np hold what an earlier frame left: every reader tests level or the
    # band's samples first)


@serial
def _store_row(y, width, hits, hits2, frustum, frame, view, prev_hits, prev_hits2, prev, same, tests, reuse, fov):
    """Row y of `frame`, rendered as presampled (its colour and depth, which the tracer wrote into its history
    slot, and hits and hits2: its primary and secondary hits) at its band's class (fov.samples), the presampled
    colour kept as ref where the tests read it (fov.table1); with `reuse`, kim2021 section 4.4's test per
    central pixel with a hit: back-projected into the previous frame (through its relative_view `view`; onto
    itself when `same`) it must meet a hit within rel_depth of its distance, reused fewer than n_reuse_max times
    in a row and rendered at no lower class than the pixel needs now, whose presampled colour passes section 3's
    two-step test against the pixel's (tau_sel from Table 1's geometry attributes at the primary and the secondary
    hit, then the contrast at tau_sel x tau_reuse), with the drift of where its colour was sampled staying within
    reuse_px; it takes that pixel's rendered colour, class and drift then. Returns the row's reused pixels."""
    ref, depth, flags, rendered, level, drift = frame
    prev_ref, prev_depth, prev_flags, prev_rendered, prev_level, prev_drift = prev
    obj, ns, shadow, tex = _geometry(hits)
    obj2, ns2, shadow2, tex2 = _geometry(hits2)
    prev_obj, prev_ns, prev_shadow, prev_tex = _geometry(prev_hits)
    prev_obj2, prev_ns2, prev_shadow2, prev_tex2 = _geometry(prev_hits2)
    thresholds, normal_cos, tau_reuse, n_max, rel_depth, reuse_px = tests
    taus, taus2 = _taus(thresholds)
    samples, table1 = fov.samples, fov.table1
    height = depth.shape[0] // width
    reused = 0
    for x in range(width):
        i = np.uint64(y * width + x)  # unsigned indices: no negative-index wraparound on the loads and stores
        level[i] = samples[i]
        if table1[i]:
            for c in range(3):
                ref[i, c] = rendered[i, c]
        if samples[i] == 0:  # peripheral: nothing reads its flags and drift (Kept), nor its depth and id here
            continue
        flags[i] = 0
        drift[i, 0] = drift[i, 1] = 0.0
        d = depth[i]
        if not reuse or math.isinf(d) or obj[i] < 0:
            continue
        j, dist, ox, oy = y * width + x, min(np.float64(d), FAR), 0.0, 0.0
        if not same:
            px, py, pz = eye_point(frustum, x + 0.5, y + 0.5, d)
            qx, qy, dist = view_project(view, px, py, pz)
            j = nearest_index(qx, qy, width, height)
            ox, oy = qx - (j % width + 0.5), qy - (j // width + 0.5)
        if j < 0:
            continue
        j = np.uint64(j)
        if prev_level[j] < samples[i] or prev_flags[j] >= n_max:  # a level of 0: not central, its flags stale
            continue
        if math.isinf(prev_depth[j]) or prev_obj[j] < 0 or abs(prev_depth[j] - dist) > rel_depth * dist:
            continue
        dx, dy = prev_drift[j, 0] - ox, prev_drift[j, 1] - oy
        if dx * dx + dy * dy > reuse_px * reuse_px:
            continue
        at_primary = _discordant_threshold(
            obj[i], prev_obj[j], _dot(ns, i, prev_ns, j), shadow[i], prev_shadow[j], tex[i], prev_tex[j], taus,
            normal_cos,
        )  # fmt: skip
        at_secondary = _discordant_threshold(
            obj2[i], prev_obj2[j], _dot(ns2, i, prev_ns2, j), shadow2[i], prev_shadow2[j], tex2[i], prev_tex2[j], taus2,
            normal_cos,
        )  # fmt: skip
        tau = min(at_primary, at_secondary)
        tau = thresholds[0] if tau == math.inf else tau
        if _pair_contrast_fails(_rgb(ref, i), _rgb(prev_ref, j), tau * tau_reuse):
            continue
        flags[i], level[i] = prev_flags[j] + 1, prev_level[j]
        drift[i, 0], drift[i, 1] = dx, dy
        for c in range(3):
            rendered[i, c] = prev_rendered[j, c]
        reused += 1
    return reused


@kernel
def _clear(width, hits, spans):
    """Every hit of the pixels the tests read (Foveation.table1: those with a central pixel, of `spans`, among their
    8 neighbours) a miss, in its object id alone: the tests read no other attribute of a miss
    (disparity._discordant_threshold), the tracer fills the secondary hits it finds there, and nothing reads the
    other pixels' hits."""
    obj = hits.object_id
    height = obj.shape[0] // width
    for y in nb.prange(height):
        first, last = width, 0
        for row in range(max(y - 1, 0), min(y + 2, height)):
            if spans[row, 1] > spans[row, 0]:
                first, last = min(first, spans[row, 0] - 1), max(last, spans[row, 1] + 1)
        for x in range(max(first, 0), min(last, width)):
            obj[y * width + x] = -1


@kernel
def _store(
    width,
    hits,
    hits2,
    frustum,
    frame,
    view,
    prev_hits,
    prev_hits2,
    prev,
    same,
    tests,
    reuse,
    fov,
    counter,
    threads,
):
    """_store_row over the image, rows claimed (hmdrt.kernels.schedule: a row of reused pixels costs more); returns the
    number of reused pixels. Each frame's G-buffer comes as its two halves (a parallel loop takes no nested tuple)."""
    reused = 0
    h = frame.depth.shape[0] // width
    for _ in nb.prange(threads):
        y = claim(counter)
        while y < h:
            reused += _store_row(
                y,
                width,
                hits,
                hits2,
                frustum,
                frame,
                view,
                prev_hits,
                prev_hits2,
                prev,
                same,
                tests,
                reuse,
                fov,
            )
            y = claim(counter)
    return reused
