"""Error against run time: every cell of an eval config (scene x profile x trace x method setting) rendered in
virtual time, timed per frame, and scored per eccentricity band against the cached ground truth.

Within a scene, profile and trace the methods render frame by frame in turn, so that load on a shared machine
hits every method alike; the first warmup_frames frames (empty temporal history, RRM's first refresh cycle) are
rendered but neither timed nor scored (full and regular, which keep no history, skip them). ms_per_frame is the
median of the timed frames.
"""

from __future__ import annotations

import itertools
import os
import platform
import statistics
import time
from dataclasses import dataclass, field
from functools import partial

import numpy as np
from tqdm import tqdm

from hmdrt.evaluate.config import EvalConfig
from hmdrt.evaluate.perceptual import JodScorer
from hmdrt.evaluate.truth import TruthCache, scene_digest
from hmdrt.foveation import Method, MethodChoice
from hmdrt.optics import get_profile
from hmdrt.optics.camera import eccentricity_map
from hmdrt.quality import BandScores
from hmdrt.scene import load_scene
from hmdrt.sequence import eye_cameras, frame_requests, sequence_inputs
from hmdrt.telemetry.stats import RAY_KINDS, FrameStats
from hmdrt.trace.integrator import Whitted

REFERENCES = ("full", "regular")  # not foveated (never the "best foveated" cell) and stateless (no warm-up)


@dataclass
class _Cell:
    choice: MethodChoice
    label: str
    method: Method
    scores: BandScores = field(default_factory=BandScores)
    ms: list[float] = field(default_factory=list)
    rays: list[int] = field(default_factory=list)
    fractions: list[float] = field(default_factory=list)
    stages_ms: dict[str, float] = field(default_factory=dict)  # summed over the timed frames, top-level stages
    jod: list[float] = field(default_factory=list)
    rays_by_kind: dict[str, int] = field(default_factory=lambda: dict.fromkeys(RAY_KINDS, 0))  # summed likewise
    last: np.ndarray | None = None


@dataclass
class Crops:
    """The last scored frame of one scene, profile and trace: the truth, each method's image, the gaze pixel."""

    scene: str
    profile: str
    trace: str
    truth: np.ndarray
    images: dict[str, np.ndarray]
    gaze_xy: tuple[float, float]


@dataclass
class Evaluation:
    rows: list[dict]
    summary: list[dict]
    crops: list[Crops]
    truths_rendered: int
    truths_read: int
    seconds: float

    def to_dict(self, config: EvalConfig) -> dict:
        return {
            "config": config.source,
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
            "seconds": round(self.seconds, 1),
            "truth": {
                "method": f"regular?spp={config.truth_spp}",
                "cache_dir": config.cache_dir,
                "rendered": self.truths_rendered,
                "read": self.truths_read,
            },
            "summary": self.summary,
            "rows": self.rows,
        }


def _profile(name: str, resolution: str):
    profile = get_profile(name)
    return profile.with_resolution_text(resolution, "resolution") if resolution else profile


def evaluate(config: EvalConfig, progress: bool = True) -> Evaluation:
    """Render and score every cell of `config`; a progress bar on stderr when `progress` and it is a terminal."""
    started = time.perf_counter()
    cache = TruthCache(config.cache_dir, config.truth_spp, config.seed)
    cells_per_scene = sum(len(config.cells(scene)) for scene in config.scenes)
    total = len(config.profiles) * len(config.traces) * config.frames * cells_per_scene
    rows: list[dict] = []
    crops: list[Crops] = []
    with tqdm(total=total, unit="frame", disable=None if progress else True, leave=False) as bar:
        for scene_name in config.scenes:
            if not config.cells(scene_name):
                continue
            scene = load_scene(scene_name)
            with Whitted(scene, threads=config.threads or None) as tracer:
                truth = partial(cache.get, tracer, scene_digest(scene))
                for profile_name, trace in itertools.product(config.profiles, config.traces):
                    profile = _profile(profile_name, config.resolution)
                    bar.set_description(f"{scene_name} {profile_name} {trace.label}")
                    group = {"scene": scene_name, "profile": profile.name, "trace": trace.label}
                    inputs, _ = sequence_inputs(
                        scene.start,
                        profile.period_ns,
                        config.frames,
                        trace=trace.source,
                        gaze=trace.gaze or "0,0",
                        seed=config.seed,
                    )
                    cells = [
                        _Cell(choice, label, choice.make(tracer)) for choice, label in config.cells(scene_name).items()
                    ]
                    jod = JodScorer(profile, config.eye) if config.jod else None
                    last = _render(inputs, cells, profile, truth, config, bar.update, jod)
                    rows += _rows(group, cells, profile)
                    crops.append(Crops(**group, **last, images={c.label: c.last for c in cells}))
    return Evaluation(rows, summarise(rows), crops, cache.rendered, cache.read, time.perf_counter() - started)


def _render(inputs, cells: list[_Cell], profile, truth_of, config: EvalConfig, tick, jod: JodScorer | None) -> dict:
    """Each input frame through every cell's method in turn; the frames after the warm-up timed and scored.
    Returns the last scored frame's truth and gaze pixel."""
    last: dict = {}
    for inp in inputs:
        [request] = frame_requests(inp, eye_cameras(profile, inp.pose, (config.eye,)), config.seed)
        scored = inp.frame >= config.warmup_frames
        if scored:
            truth = truth_of(request.camera)
            eccentricity = eccentricity_map(request.camera, request.gaze)
            last = {"truth": truth, "gaze_xy": tuple(float(v) for v in request.camera.gaze_pixel(request.gaze))}
        for cell in cells:
            if not scored and cell.method.name in REFERENCES:
                tick()  # stateless: nothing to warm up
                continue
            stats = FrameStats()
            t = time.perf_counter()
            image = cell.method.render(request, stats)
            ms = (time.perf_counter() - t) * 1e3
            if scored:
                pixels = image.shape[0] * image.shape[1]
                cell.ms.append(ms)
                cell.rays.append(sum(stats.rays.values()))
                for kind, n in stats.rays.items():
                    cell.rays_by_kind[kind] += n
                cell.fractions.append(stats.metrics.get("sample_fraction", stats.rays["primary"] / pixels))
                cell.scores.add(image, truth, eccentricity)
                cell.last = image.copy()
                if jod is not None:
                    cell.jod.append(jod.score(image, truth, last["gaze_xy"]))
                for stage, stage_ms in stats.stages_ms.items():
                    if "/" not in stage:
                        cell.stages_ms[stage] = cell.stages_ms.get(stage, 0.0) + stage_ms
            tick()
    return last


def _rows(group: dict, cells: list[_Cell], profile) -> list[dict]:
    rows = []
    for cell in cells:
        rows.append(
            {
                **group,
                "width": profile.width,
                "height": profile.height,
                "method": cell.choice.name,
                "params": str(cell.choice),
                "label": cell.label,
                "frames": len(cell.ms),
                "ms_per_frame": round(statistics.median(cell.ms), 3),
                "rays_per_frame": round(float(np.mean(cell.rays))),
                **{f"rays_{k}": round(n / len(cell.ms)) for k, n in cell.rays_by_kind.items()},
                "sample_fraction": round(float(np.mean(cell.fractions)), 5),
                **{k: _round(v) for k, v in cell.scores.result().items()},
                **({"jod": round(float(np.mean(cell.jod)), 4)} if cell.jod else {}),
                "stages_ms": {k: round(v / len(cell.ms), 3) for k, v in cell.stages_ms.items()},
            }
        )
    full = next((r for r in rows if r["method"] == "full"), None)
    for row in rows:
        row["speedup_vs_full"] = round(full["ms_per_frame"] / row["ms_per_frame"], 3) if full else None
    front = pareto_front([(r["ms_per_frame"], r["psnr_fovea"]) for r in rows])
    for row, on in zip(rows, front, strict=True):
        row["pareto"] = on
    return rows


def _round(value: float | None) -> float | None:
    return None if value is None else value if not np.isfinite(value) else round(value, 5)


def pareto_front(points: list[tuple[float, float | None]]) -> list[bool]:
    """Which (time, quality) points no other point beats: at most as slow and at least as good, one strictly
    (a point without a quality is never on the front)."""

    def beats(a: tuple[float, float], b: tuple[float, float]) -> bool:
        return a[0] <= b[0] and a[1] >= b[1] and (a[0] < b[0] or a[1] > b[1])

    scored = [(t, q) for t, q in points if q is not None]
    return [q is not None and not any(beats(o, (t, q)) for o in scored) for t, q in points]


def summarise(rows: list[dict]) -> list[dict]:
    """Per scene, profile and trace: full's time and foveal PSNR, and the fastest foveated cell on the Pareto
    front whose foveal PSNR is at least full's (issue 6's criterion), with its speed-up."""
    out = []
    groups = dict.fromkeys((r["scene"], r["profile"], r["trace"]) for r in rows)
    for scene, profile, trace in groups:
        group = [r for r in rows if (r["scene"], r["profile"], r["trace"]) == (scene, profile, trace)]
        full = next((r for r in group if r["method"] == "full"), None)
        entry = {"scene": scene, "profile": profile, "trace": trace, "full_ms": None, "full_psnr_fovea": None}
        best = None
        if full is not None:
            entry.update(full_ms=full["ms_per_frame"], full_psnr_fovea=full["psnr_fovea"])
            candidates = [
                r
                for r in group
                if r["pareto"]
                and r["method"] not in REFERENCES
                and r["psnr_fovea"] is not None
                and full["psnr_fovea"] is not None
                and r["psnr_fovea"] >= full["psnr_fovea"]
            ]
            best = min(candidates, key=lambda r: r["ms_per_frame"], default=None)
        entry.update(
            best=None if best is None else best["label"],
            best_ms=None if best is None else best["ms_per_frame"],
            best_psnr_fovea=None if best is None else best["psnr_fovea"],
            best_speedup=None if best is None else best["speedup_vs_full"],
        )
        out.append(entry)
    return out
