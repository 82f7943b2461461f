"""Error against run time: every cell of an eval config (scene x profile x trace x method setting) rendered in
virtual time, timed per frame, and scored per eccentricity band against the cached ground truth.

Within a scene, profile and trace the methods render frame by frame in turn, so that load on a shared machine
hits every method alike. Warm-up frames come first, rendered but neither timed nor scored: the trace's first
warmup_frames frames, and where a method of the group declares a longer history (Method.warmup_frames: RRM's
refresh cycle) as many more frames before them holding the trace's first frame, so that no method is scored
before its images are steady and every group scores the same frames of the trace; methods without history
(warmup_frames 0: full, regular) skip them. The trace's frames after its first warmup_frames follow, timed and
scored; ms_per_frame is their median. Each cell is compared with a baseline cell (its compare_to, else full):
speed-up and foveal PSNR delta.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import os
import platform
import statistics
import time
from dataclasses import dataclass, field
from functools import partial

import msgspec
import numpy as np
from tqdm import tqdm

from hmdrt.evaluate.config import EvalConfig
from hmdrt.evaluate.perceptual import JodScorer, encode
from hmdrt.evaluate.truth import TruthCache, scene_digest
from hmdrt.foveation import Method, MethodChoice
from hmdrt.optics import get_profile
from hmdrt.optics.camera import eccentricity_map
from hmdrt.quality import BandScores, ScoreSpace
from hmdrt.scene import load_scene
from hmdrt.sequence import FrameInput, eye_cameras, frame_requests, sequence_inputs
from hmdrt.telemetry.stats import RAY_KINDS, FrameStats
from hmdrt.trace.integrator import Whitted

REFERENCES = ("full", "regular")  # not foveated: never the "best foveated" cell of the summary
log = logging.getLogger(__name__)


@dataclass
class _Cell:
    choice: MethodChoice
    label: str
    compare_to: str  # the label of the baseline cell ("": full)
    method: Method
    scores: BandScores
    ms: list[float] = field(default_factory=list)
    rays: list[int] = field(default_factory=list)
    fractions: list[float] = field(default_factory=list)
    stages_ms: dict[str, float] = field(default_factory=dict)  # summed over the timed frames, top-level stages
    frames: list[np.ndarray] = field(default_factory=list)  # the scored frames, display-encoded (with jod only)
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
    score_space: ScoreSpace

    def to_dict(self, config: EvalConfig) -> dict:
        return {
            "config": config.source,
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform()},
            "seconds": round(self.seconds, 1),
            "score_space": self.score_space,
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
    cells = sum(len(config.cells(scene, trace)) for scene in config.scenes for trace in config.traces)
    total = len(config.profiles) * config.frames * cells
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
                    if not config.cells(scene_name, trace):
                        continue
                    profile = _profile(profile_name, config.resolution)
                    bar.set_description(f"{scene_name} {profile_name} {trace.label}")
                    group = {"scene": scene_name, "profile": profile.name, "trace": trace.label}
                    cells = [
                        _Cell(*cell, cell.choice.make(tracer), BandScores(config.score_space))
                        for cell in config.cells(scene_name, trace)
                    ]
                    warmup = group_warmup(config.warmup_frames, cells, group)
                    bar.total += (warmup - config.warmup_frames) * len(cells)
                    inputs, _ = sequence_inputs(
                        scene.start, profile.period_ns, config.frames, trace.source, trace.gaze or "0,0", config.seed
                    )
                    inputs = held_start(inputs, warmup - config.warmup_frames, profile.period_ns)
                    last, scored = _render(inputs, cells, profile, truth, config, warmup, bar.update)
                    jod = _jod(cells, scored, JodScorer(profile, config.eye)) if config.jod else {}
                    rows += [
                        {**row, "trace_group": trace.group_label, **jod.get(row["label"], {})}
                        for row in _rows(group, cells, profile, warmup, config.score_space)
                    ]
                    crops.append(Crops(**group, **last, images={c.label: c.last for c in cells}))
    seconds = time.perf_counter() - started
    return Evaluation(rows, summarise(rows), crops, cache.rendered, cache.read, seconds, config.score_space)


def held_start(inputs: list[FrameInput], extra: int, period_ns: int) -> list[FrameInput]:
    """The trace's frames after `extra` frames that hold its first one, all renumbered from 0: a longer warm-up
    comes before the trace starts, so every group scores the same stretch of it (and its truths are shared)."""
    held = [inputs[0]] * extra + inputs
    return [dataclasses.replace(inp, frame=k, t_ns=k * period_ns) for k, inp in enumerate(held)]


def group_warmup(configured: int, cells: list[_Cell], group: dict) -> int:
    """The warm-up frames of a group: the config's, or more where a method of the group needs a longer history."""
    longest = max(cells, key=lambda c: c.method.warmup_frames)
    needed = longest.method.warmup_frames
    if needed <= configured:
        return configured
    log.info("%s: %d warm-up frames, as %s needs", " ".join(group.values()), needed, longest.label)
    return needed


def _jod(cells: list[_Cell], scored: dict, scorer: JodScorer) -> dict[str, dict]:
    """Each cell's JOD ({label: {"jod": value}}): its scored frames as one video against the truths'."""
    truths, gazes = scored["truths"], scored["gazes"]
    return {c.label: {"jod": round(scorer.score(c.frames, truths, gazes), 4)} for c in cells}


def _render(inputs, cells: list[_Cell], profile, truth_of, config: EvalConfig, warmup: int, tick) -> tuple[dict, dict]:
    """Each input frame through every cell's method in turn; the frames after the warm-up timed and scored.
    Returns the last scored frame's truth and gaze pixel, and (with jod) every scored truth, encoded, and gaze."""
    last: dict = {}
    truths, gazes = [], []
    for inp in inputs:
        [request] = frame_requests(inp, eye_cameras(profile, inp.pose, (config.eye,)), config.seed)
        scored = inp.frame >= warmup
        if scored:
            truth = truth_of(request.camera)
            eccentricity = eccentricity_map(request.camera, request.gaze)
            last = {"truth": truth, "gaze_xy": tuple(float(v) for v in request.camera.gaze_pixel(request.gaze))}
            if config.jod:
                truths.append(encode(truth))
                gazes.append(last["gaze_xy"])
        for cell in cells:
            if not scored and not cell.method.warmup_frames:
                tick()  # no history: nothing to warm up
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
                if config.jod:
                    cell.frames.append(encode(image))
                for stage, stage_ms in stats.stages_ms.items():
                    if "/" not in stage:
                        cell.stages_ms[stage] = cell.stages_ms.get(stage, 0.0) + stage_ms
            tick()
    return last, {"truths": truths, "gazes": gazes}


def _rows(group: dict, cells: list[_Cell], profile, warmup: int, space: ScoreSpace) -> list[dict]:
    rows = []
    for cell in cells:
        rows.append(
            {
                **group,
                "width": profile.width,
                "height": profile.height,
                "method": cell.choice.name,
                "params": str(cell.choice),
                "options": msgspec.to_builtins(cell.choice.params),
                "label": cell.label,
                "frames": len(cell.ms),
                "warmup_frames": warmup if cell.method.warmup_frames else 0,
                "ms_per_frame": round(statistics.median(cell.ms), 3),
                "rays_per_frame": round(float(np.mean(cell.rays))),
                **{f"rays_{k}": round(n / len(cell.ms)) for k, n in cell.rays_by_kind.items()},
                "sample_fraction": round(float(np.mean(cell.fractions)), 5),
                "score_space": space,
                **{k: _round(v) for k, v in cell.scores.result().items()},
                "stages_ms": {k: round(v / len(cell.ms), 3) for k, v in cell.stages_ms.items()},
            }
        )
    full = next((r for r in rows if r["method"] == "full"), None)
    for row, cell in zip(rows, cells, strict=True):
        row["speedup_vs_full"] = round(full["ms_per_frame"] / row["ms_per_frame"], 3) if full else None
        baseline = next((r for r in rows if r["label"] == cell.compare_to), None) if cell.compare_to else full
        row.update(_comparison(row, baseline))
    front = pareto_front([(r["ms_per_frame"], r["psnr_fovea"]) for r in rows])
    for row, on in zip(rows, front, strict=True):
        row["pareto"] = on
    return rows


def _comparison(row: dict, baseline: dict | None) -> dict:
    """The row against its baseline row: the baseline's label, the speed-up and the foveal PSNR delta (dB)."""
    if baseline is None:
        return {"baseline": None, "speedup_vs_baseline": None, "psnr_fovea_vs_baseline": None}
    return {
        "baseline": baseline["label"],
        "speedup_vs_baseline": round(baseline["ms_per_frame"] / row["ms_per_frame"], 3),
        "psnr_fovea_vs_baseline": _delta(row["psnr_fovea"], baseline["psnr_fovea"]),
    }


def _delta(value: float | None, baseline: float | None) -> float | None:
    """value - baseline, rounded; None where either is missing or both are infinite (the truth against itself)."""
    if value is None or baseline is None or (math.isinf(value) and value == baseline):
        return None
    return _round(value - baseline)


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
    """Per scene, profile, trace and baseline (a cell others are compared with: full unless a compare_to names
    another): the baseline's time and foveal PSNR, and the fastest foveated cell compared with it whose foveal
    PSNR is at least the baseline's (issue 6's criterion against full), with its speed-up and PSNR delta."""
    out = []
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault((r["scene"], r["profile"], r["trace"]), []).append(r)
    for (scene, profile, trace), group in groups.items():
        baselines = list(dict.fromkeys(r["baseline"] for r in group if r["baseline"] is not None)) or [None]
        for name in baselines:
            out.append({"scene": scene, "profile": profile, "trace": trace, **_best_against(group, name)})
    return out


def _best_against(group: list[dict], name: str | None) -> dict:
    """The summary of one baseline (by label; None: the group has none) and the best cell compared with it."""
    base = next((r for r in group if r["label"] == name), None) if name is not None else None
    floor = None if base is None else base["psnr_fovea"]
    candidates = [
        r
        for r in group
        if r["baseline"] == name
        and r["label"] != name
        and r["method"] not in REFERENCES
        and r["psnr_fovea"] is not None
        and floor is not None
        and r["psnr_fovea"] >= floor
    ]
    best = min(candidates, key=lambda r: (r["ms_per_frame"], -r["psnr_fovea"]), default=None)
    return {
        "baseline": name,
        "baseline_ms": None if base is None else base["ms_per_frame"],
        "baseline_psnr_fovea": floor,
        "best": None if best is None else best["label"],
        "best_ms": None if best is None else best["ms_per_frame"],
        "best_psnr_fovea": None if best is None else best["psnr_fovea"],
        "best_speedup": None if best is None else best["speedup_vs_baseline"],
        "best_psnr_fovea_delta": None if best is None else best["psnr_fovea_vs_baseline"],
    }
