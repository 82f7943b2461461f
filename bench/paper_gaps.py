"""Three gaps between configs/eval/paper_tables.toml's tables and the papers, measured (docs/evaluation.md).

    python bench/paper_gaps.py samples   # weier18's share of pixels sampled against the field of view (seconds)
    python bench/paper_gaps.py kim21     # what drives kim21's foveal gain over Selective (about 2 minutes)
    python bench/paper_gaps.py rrm       # where RRM's time goes, with and without secondary rays (about 2 minutes)

samples: weier2018 Table 1 samples 558,945 of 1,843,200 pixels (30.3%) with r0 10, r1 20, p 0.2; hmdrt 24.2%
on rift_s. The share is p_min plus the foveal excess, the integral of p(e) - p_min over the image (equation (1)
draws as many transition points as p(e) gives there), which scales with the pixels per square degree: it is
computed from each profile's eccentricity map, with weier18's own tables, and the horizontal field of view at
1280x1440 (square pixels) that gives the paper's share is solved for.

kim21: Regular_1, Selective and Sel_Fov (Table 2's settings, reuse off) and Sel_Fov with every subpixel
problematic (tau tiny: the bound of its samples alone) on a still view, scored in the fovea (< 3.3 deg, sRGB)
against regular at 36 spp, which is itself scored against 144 spp (the truth's own error caps every PSNR).
Per method: the foveal pixels supersampled, their samples, and the foveal PSNR of the pixels supersampled and of
those not.

rrm: per scene and gaze, a full frame's rays inside RRM's foveal rectangle and outside it (traced apart) and the
time of each part, the ms per frame of full and of rrm (N = 12), rrm's tracing and the rest of its frame (its
stages' shares of the frame), and the speed-up that the traced pixels' time alone would give. Times are the
process's CPU time, the median over the timed frames: on a machine shared with other work they hold where wall
times do not; run it with NUMBA_NUM_THREADS=1 so that no kernel waits for a descheduled thread.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
import time

import numpy as np

from hmdrt.evaluate import provenance
from hmdrt.evaluate.quality import BANDS, srgb_encode
from hmdrt.foveation import FrameRequest, MethodChoice
from hmdrt.foveation.base import pixel_keys
from hmdrt.foveation.rrm import RrmParams, foveal_rectangle
from hmdrt.foveation.stages.sampling import (
    Foveal,
    expected_fraction,
    pixels_per_degree,
    sampling_tables,
    table_mask,
)
from hmdrt.optics import EyeCamera, HmdProfile, get_profile
from hmdrt.optics.camera import eccentricity_map, pixel_grid
from hmdrt.optics.profiles import Fov
from hmdrt.scene import load_scene
from hmdrt.spatial import gaze_direction, parse_gaze
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace import meter
from hmdrt.trace.integrator import Whitted
from hmdrt.views import eye_cameras

WEIER18 = Foveal(10.0, 20.0, 0.2)  # weier2018 section 4.1
PAPER_SAMPLES, PAPER_PIXELS = 558_945, 1280 * 1440  # weier2018 Table 1
FOVEA_DEG = BANDS["fovea"][1]


def _camera(profile: HmdProfile, scene_name: str | None = None) -> EyeCamera:
    """The left eye's camera at the scene's start pose (the eval's still view), or at the origin looking ahead."""
    pose = load_scene(scene_name).start if scene_name else None
    if pose is None:
        from hmdrt.spatial import Pose

        pose = Pose.looking([0.0, 1.6, 0.0], 0.0, 0.0)
    return eye_cameras(profile, pose, ("left",))["left"]


def _square(h_deg: float, width: int = 1280, height: int = 1440) -> HmdProfile:
    """A symmetric profile of h_deg horizontally with square pixels at width x height."""
    v_deg = 2 * math.degrees(math.atan(math.tan(math.radians(h_deg / 2)) * height / width))
    return HmdProfile(f"{h_deg:.1f}x{v_deg:.1f} deg", width, height, Fov.symmetric(h_deg, v_deg), 70.0)


def _variants(ecc: np.ndarray, cfg: Foveal) -> dict[str, float]:
    """The expected share under p(e), and under readings of the paper that would sample more."""
    ramp = 1 - (1 - cfg.p_min) * (ecc - cfg.r0) / (cfg.r1 - cfg.r0)
    p = np.where(ecc < cfg.r0, 1.0, np.where(ecc >= cfg.r1, cfg.p_min, ramp))
    band = (ecc >= cfg.r0) & (ecc < cfg.r1)
    return {
        "p(e)": float(p.mean()),
        "S_in or S_out in the band": float(np.where(band, p + cfg.p_min * (1 - p), p).mean()),
        "band drawn at f's plain mean (1 + p)/2": float(np.where(band, (1 + cfg.p_min) / 2, p).mean()),
        "every pixel inside r1": float(np.where(ecc < cfg.r1, 1.0, p).mean()),
    }


def samples() -> None:
    """weier18's share of pixels sampled, gaze ahead, against each profile's field of view."""
    gaze = gaze_direction(*parse_gaze("0,0"))
    print(f"weier2018 Table 1: {PAPER_SAMPLES:,} of {PAPER_PIXELS:,} = {PAPER_SAMPLES / PAPER_PIXELS:.2%}")
    print(
        f"{'profile':34s} {'pixels':>10s} {'ppd x, y':>12s} {'tables':>7s} "
        + " | ".join(_variants(np.zeros(1), WEIER18))
    )
    for name, size in (("rift_s", (640, 720)), ("rift_s", (1280, 1440)), ("fove0", (1280, 1440)), ("dk2", None)):
        profile = get_profile(name) if size is None else get_profile(name).with_resolution(*size)
        _print_profile(f"{name} ({_fov_text(profile.fov)})", profile, gaze)
    lo, hi = 30.0, 120.0
    for _ in range(40):  # the share falls as the field of view grows
        mid = (lo + hi) / 2
        share = expected_fraction(eccentricity_map(_camera(_square(mid)), gaze), WEIER18)
        lo, hi = (mid, hi) if share > PAPER_SAMPLES / PAPER_PIXELS else (lo, mid)
    _print_profile(f"solved: {_square(mid).name} at 1280x1440", _square(mid), gaze)


def _fov_text(fov: Fov) -> str:
    return f"{fov.right - fov.left:.0f}x{fov.up - fov.down:.0f} deg"


def _print_profile(label: str, profile: HmdProfile, gaze: np.ndarray) -> None:
    cam = _camera(profile)
    ecc = eccentricity_map(cam, gaze)
    traced = table_mask(cam, gaze, ecc, WEIER18, sampling_tables(cam, WEIER18)).mean()
    ppd = pixels_per_degree(cam)
    shares = " | ".join(f"{v:.2%}" for v in _variants(ecc, WEIER18).values())
    print(f"{label:34s} {cam.width * cam.height:>10,d} {ppd[0]:5.2f}, {ppd[1]:5.2f} {traced:7.2%} {shares}")


def _request(profile: HmdProfile, scene_name: str, gaze: str = "0,0", frame: int = 0) -> FrameRequest:
    return FrameRequest(_camera(profile, scene_name), gaze_direction(*parse_gaze(gaze)), frame)


def _psnr(image: np.ndarray, truth: np.ndarray, where: np.ndarray) -> float:
    if not where.any():
        return math.nan
    mse = float(np.mean((srgb_encode(image)[where] - srgb_encode(truth)[where]) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(1 / mse)


KIM21 = {  # configs/eval/paper_tables.toml's settings, and Sel_Fov with every subpixel problematic
    "Regular_1": "full",
    "Selective": "kim21?tau_0=1&tau_f=1&tau_f_slope=0&tau_np=1&n_f=4&n_p=4&n_m=4&n_np=4&interpolate=false"
    "&smooth=false&reuse=false",
    "Sel_Fov": "kim21?reuse=false",
    "Sel_Fov, all problematic": "kim21?reuse=false&tau_0=1e-6&tau_f=1e-6&tau_f_slope=0&tau_np=1e-6",
}


def kim21(resolution: str, scenes: list[str], frames: int) -> None:
    """Foveal PSNR of each method's last frame (the view still for `frames` frames) and what its fovea sampled."""
    profile = get_profile("rift_s").with_resolution_text(resolution)
    for scene_name in scenes:
        with Whitted(load_scene(scene_name)) as tracer:
            request = _request(profile, scene_name)
            truth = MethodChoice.parse("regular?spp=36").make(tracer).render(request, FrameStats())
            finer = MethodChoice.parse("regular?spp=144").make(tracer).render(request, FrameStats())
            other = dataclasses.replace(request, seed=1)
            again = MethodChoice.parse("regular?spp=36").make(tracer).render(other, FrameStats())
            fovea = eccentricity_map(request.camera, request.gaze) < FOVEA_DEG
            print(f"\n{scene_name} at {resolution}, gaze ahead, {int(fovea.sum())} foveal pixels; the truth (36 spp) "
                  f"against 144 spp: {_psnr(truth, finer, fovea):.1f} dB in the fovea; 36 spp of another seed "
                  f"against the truth: {_psnr(again, truth, fovea):.1f} dB")  # fmt: skip
            print(f"{'method':26s} {'fovea dB':>8s} {'vs 144':>7s} {'supersampled':>12s} {'spp':>5s} "
                  f"{'dB there':>8s} {'dB not':>7s} {'error not':>9s}")  # fmt: skip
            for label, spec in KIM21.items():
                method = MethodChoice.parse(spec).make(tracer)
                for k in range(frames):
                    image = method.render(_request(profile, scene_name, frame=k), FrameStats())
                _print_kim21(label, method, image, truth, finer, fovea)


def _print_kim21(label: str, method, image: np.ndarray, truth: np.ndarray, finer: np.ndarray, fovea: np.ndarray):
    h, w = fovea.shape
    if method.name == "kim21":
        state = method._eyes["left"]  # noqa: SLF001 - the last frame's problematic subpixels, for the bench only
        bits = np.unpackbits(state.sub_mask.reshape(h, w)[..., None], axis=-1)[..., 4:].sum(axis=-1)
        extra = bits * state.fov.samples.reshape(h, w)
    else:
        extra = np.zeros((h, w), int)
    sampled = fovea & (extra > 0)
    err = np.mean((srgb_encode(image) - srgb_encode(truth)) ** 2, axis=-1)
    share = float(err[fovea & ~sampled].sum() / err[fovea].sum()) if err[fovea].sum() else 0.0
    print(f"{label:26s} {_psnr(image, truth, fovea):8.2f} {_psnr(image, finer, fovea):7.2f} "
          f"{sampled.sum() / fovea.sum():12.1%} {1 + extra[fovea].mean():5.1f} {_psnr(image, truth, sampled):8.2f} "
          f"{_psnr(image, truth, fovea & ~sampled):7.2f} {share:9.1%}")  # fmt: skip


RRM_SCENES = ("whitted", "whitted?max_depth=0", "bunny?max_depth=0")


def rrm(resolution: str, gazes: list[str], frames: int) -> None:
    """Rays by kind in RRM's fovea and outside it, and ms per frame of full and rrm, per scene and gaze."""
    profile = get_profile("rift_s").with_resolution_text(resolution)
    params = RrmParams()
    print(f"{'scene':20s} {'gaze':7s} {'fovea px':>8s} {'secondary in fovea':>18s} {'rays in fovea':>13s} "
          f"{'trace ms fovea, rest':>20s} {'full ms':>7s} {'rrm ms':>6s} {'rrm trace':>9s} {'rrm other':>9s} "
          f"{'x':>5s} {'x by rays':>9s} {'rays full, rrm (k)':>18s}")  # fmt: skip
    for scene_name in RRM_SCENES:
        with Whitted(load_scene(scene_name)) as tracer:
            for gaze in gazes:
                _print_rrm(tracer, profile, params, scene_name, gaze, frames)


def _trace_part(tracer: Whitted, cam: EyeCamera, xy: np.ndarray, keys: np.ndarray, repeats: int) -> FrameStats:
    """The stats of tracing these pixels, "trace" the median CPU ms of `repeats`."""
    times, stats = [], FrameStats()
    for _ in range(repeats):
        stats = FrameStats()
        started = time.process_time()
        tracer.trace_samples(cam, xy, keys, stats)
        times.append((time.process_time() - started) * 1e3)
    stats.stages_ms = {"trace": statistics.median(times)}
    return stats


def _print_rrm(tracer: Whitted, profile: HmdProfile, params: RrmParams, scene_name: str, gaze: str, frames: int):
    request = _request(profile, scene_name, gaze)
    cam = request.camera
    x0, x1, y0, y1 = foveal_rectangle(cam, request.gaze, params)
    xy = pixel_grid(cam.width, cam.height)
    inside = np.zeros((cam.height, cam.width), bool)
    inside[y0:y1, x0:x1] = True
    inside = inside.ravel()
    keys = pixel_keys(np.arange(len(xy)), 0)
    fov, rest = (_trace_part(tracer, cam, xy[m], keys[m], frames) for m in (inside, ~inside))
    full = MethodChoice.parse("full").make(tracer)
    method = MethodChoice.parse("rrm").make(tracer)
    full_ms, rrm_ms, rrm_trace, rrm_rays = [], [], [], []
    for k in range(method.warmup_frames + frames):
        req = _request(profile, scene_name, gaze, k)
        for m, out in ((full, full_ms), (method, rrm_ms)):
            stats = FrameStats()
            started, wall = time.process_time(), time.perf_counter()
            m.render(req, stats)
            cpu_ms, wall_ms = (time.process_time() - started) * 1e3, (time.perf_counter() - wall) * 1e3
            if k >= method.warmup_frames:
                out.append(cpu_ms)
                if m is method:  # its tracing's share of the frame's wall time, of its CPU time
                    traced = sum(stats.stages_ms.get(stage, 0.0) for stage in meter.STAGES)
                    rrm_trace.append(cpu_ms * traced / wall_ms)
                    rrm_rays.append(sum(stats.rays.values()))
    secondary = fov.rays["secondary"] / max(1, fov.rays["secondary"] + rest.rays["secondary"])
    full_rays = sum(fov.rays.values()) + sum(rest.rays.values())
    rays_in = sum(fov.rays.values()) / full_rays
    f_ms, r_ms, o_ms = fov.stages_ms["trace"], rest.stages_ms["trace"], statistics.median(rrm_ms)
    t_ms = statistics.median(rrm_trace)
    by_rays = (f_ms + r_ms) / (f_ms + r_ms / params.cycle)
    print(f"{scene_name:20s} {gaze:7s} {int(inside.sum()):8d} {secondary:18.1%} {rays_in:13.1%} "
          f"{f_ms:9.1f}, {r_ms:8.1f} {statistics.median(full_ms):7.1f} {o_ms:6.1f} {t_ms:9.1f} {o_ms - t_ms:9.1f} "
          f"{statistics.median(full_ms) / o_ms:5.2f} {by_rays:9.2f} "
          f"{full_rays / 1e3:10.0f}, {statistics.fmean(rrm_rays) / 1e3:6.0f}")  # fmt: skip


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("what", choices=("samples", "kim21", "rrm"))
    parser.add_argument("--resolution", default="320x360", help="per-eye WIDTHxHEIGHT at rift_s's optics (kim21, rrm)")
    parser.add_argument("--scenes", default="tunnel_maps,whitted", help="kim21's scenes, comma-separated")
    parser.add_argument("--gazes", default="0,0;20,0;-20,15", help="rrm's gazes (YAW,PITCH), semicolon-separated")
    parser.add_argument("--frames", type=int, default=5, help="kim21: frames of the still view; rrm: timed frames")
    args = parser.parse_args()
    stamp = provenance.stamp()
    print(f"{' '.join(sys.argv)}: {stamp['date']}, commit {stamp['commit']}, {stamp['machine']}")
    if args.what == "samples":
        samples()
    elif args.what == "kim21":
        kim21(args.resolution, args.scenes.split(","), args.frames)
    else:
        rrm(args.resolution, args.gazes.split(";"), args.frames)
    return 0


if __name__ == "__main__":
    sys.exit(main())
