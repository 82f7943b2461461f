"""Error against run time: every cell of an eval config (scene x profile x trace x method setting) rendered in virtual
time, timed per frame, and scored per eccentricity band against the cached ground truth.

Within a scene, profile and trace the methods render frame by frame in turn, so that load on a shared machine hits
every method alike. Warm-up frames come first, rendered but neither timed nor scored: the trace's first
warmup_frames frames, and where a method of the group declares a longer history (Method.warmup_frames: RRM's refresh
cycle) as many more frames before them holding the trace's first frame, so that no method is scored before its
images are steady and every group scores the same frames of the trace; methods without history (warmup_frames 0:
full, regular) skip them. The trace's frames after its first warmup_frames follow, timed and scored. Timing rounds
repeat that from fresh method instances, timed and not scored (timing_rounds, the first round being the scored one):
ms_per_frame is the median over the rounds of each round's mean (a mean over the frames, so that a frame shorter
than the scheduler's time slice counts its share of preemption rather than all or none of it), cpu_ms_per_frame the
same of the process's CPU time, and a speed-up whose round-by-round ratios spread by more than NOISY_SPREAD of their
median is marked noisy and left out of the summary's best cells. Each number a method reports per frame
(FrameStats.metrics: sample_fraction, reused_pixels, ...) is averaged over the scored frames that report it into the
row's metrics. Each cell is compared with a baseline cell (its compare_to, else full): speed-up and foveal PSNR
delta. The rows say when, at which commit and on which machine they were rendered (provenance).

A method renders each frame around the gaze its trace's eye tracker reported and from the head pose its head tracker
reported, each late and predicted (hmdrt.evaluate.gaze; the true gaze and pose themselves by default); the scores
follow the true gaze, against ground truths rendered at the true pose. The rows give the latencies, the trackers,
the gaze and head orientation errors at photon time over the scored frames, and the share of them whose gaze error
exceeds the method's foveal radius.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import numbers
import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial

import msgspec
import numpy as np
from tqdm import tqdm

from hmdrt.evaluate import gaze, provenance
from hmdrt.evaluate.config import EvalConfig
from hmdrt.evaluate.groups import Crops, GroupKey, GroupResult, group_id, group_shape, groups, profile_of
from hmdrt.evaluate.partial import PartialResults
from hmdrt.evaluate.perceptual import JodScorer, encode
from hmdrt.evaluate.quality import BandScores, ScoreSpace
from hmdrt.evaluate.truth import TruthCache, scene_digest
from hmdrt.foveation import FrameRequest, Method, MethodChoice
from hmdrt.optics import EyeCamera, HmdProfile
from hmdrt.optics.camera import eccentricity_map
from hmdrt.scene import Scene, load_scene
from hmdrt.telemetry.stats import RAY_KINDS, FrameStats
from hmdrt.trace.integrator import Whitted
from hmdrt.views import FrameInput, eye_cameras, frame_requests, held_start, sequence_inputs

REFERENCES = ("full", "regular")  # not foveated: never the "best foveated" cell of the summary
NOISY_SPREAD = 0.15  # a speed-up whose per-round ratios range over more than this of their median is noisy
log = logging.getLogger(__name__)


@dataclass
class _Cell:
    choice: MethodChoice
    label: str
    compare_to: str  # the label of the baseline cell ("": full)
    method: Method
    scores: BandScores
    ms: list[list[float]] = field(default_factory=list)  # per timing round, each timed frame's wall ms
    cpu_ms: list[list[float]] = field(default_factory=list)  # and the process's CPU ms
    rays: list[int] = field(default_factory=list)
    fractions: list[float] = field(default_factory=list)
    metrics: dict[str, list[float]] = field(default_factory=dict)  # each metric's finite values, frame by frame
    stages_ms: dict[str, float] = field(default_factory=dict)  # summed over the timed frames, top-level stages
    frames: list[np.ndarray] = field(default_factory=list)  # the scored frames, display-encoded (with jod only)
    rays_by_kind: dict[str, int] = field(default_factory=lambda: dict.fromkeys(RAY_KINDS, 0))  # summed likewise
    last: np.ndarray | None = None


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
            "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "cpu": provenance.machine()},
            "commit": provenance.commit(),
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


@dataclass
class Group:
    """A group ready to render: its cells' methods built, its warm-up and its frames (warm-up first), true and as
    the methods see them."""

    key: GroupKey
    profile: HmdProfile
    tracer: Whitted  # of the group's scene: the timing rounds build their fresh methods on it
    ids: dict[str, str]  # scene, profile, trace: the columns that name the group in every row
    cells: list[_Cell]
    warmup: int
    inputs: list[FrameInput]
    seen: list[FrameInput]  # inputs with the gaze and pose the methods are given


def evaluate(config: EvalConfig, progress: bool = True, saved: PartialResults | None = None) -> Evaluation:
    """Render and score every cell of `config` in this process; a progress bar on stderr when `progress` and it is
    a terminal. With `saved`, each finished group is added to it and the groups it holds are not rendered again."""
    started = time.perf_counter()
    cache = TruthCache(config.cache_dir, config.truth_spp, config.seed)
    results = dict(saved.done) if saved else {}
    todo = [key for key in groups(config) if group_id(config, key) not in results]
    total = config.timing_rounds * config.frames * sum(len(config.cells(key.scene, key.trace)) for key in todo)
    with tqdm(total=total, unit="frame", disable=None if progress else True, leave=False) as bar:
        for scene_name, keys in itertools.groupby(todo, key=lambda k: k.scene):
            scene = load_scene(scene_name)
            with Whitted(scene, threads=config.threads or None) as tracer:
                truth = partial(cache.get, tracer, scene_digest(scene))
                for key in keys:
                    group = plan_group(config, tracer, key, trace_frames(config, scene, key))
                    bar.total += config.timing_rounds * (group.warmup - config.warmup_frames) * len(group.cells)
                    bar.set_description(" ".join(group.ids.values()))
                    result = run_group(group, config, truth, bar.update)
                    results[group_id(config, key)] = result
                    if saved:
                        saved.add(group_id(config, key), result)
    return collect(config, results, cache.rendered, cache.read, started)


def collect(
    config: EvalConfig, results: dict[str, GroupResult], rendered: int, read: int, started: float
) -> Evaluation:
    """The evaluation of every group's result (by group_id), in the config's order."""
    ordered = [results[group_id(config, key)] for key in groups(config)]
    rows = [row for result in ordered for row in result.rows]
    seconds = time.perf_counter() - started
    return Evaluation(rows, summarise(rows), [r.crops for r in ordered], rendered, read, seconds, config.score_space)


def trace_frames(config: EvalConfig, scene: Scene, key: GroupKey) -> gaze.TraceFrames:
    """A group's frames of its trace, true and as its trackers show them, read here (where the group renders
    elsewhere, it is sent them)."""
    profile = profile_of(key.profile, config.resolution)
    trace = key.trace
    source, fixed = trace.source, trace.gaze or "0,0"
    true = sequence_inputs(scene.start, profile.period_ns, config.frames, source, fixed, config.seed)[0]
    return gaze.TraceFrames(true, gaze.seen_frames(trace, true, scene.start, config.seed))


def plan_group(config: EvalConfig, tracer: Whitted, key: GroupKey, frames: gaze.TraceFrames) -> Group:
    """A group's methods built on `tracer` (of its scene), its warm-up, and its trace's `frames` after it."""
    profile = profile_of(key.profile, config.resolution)
    ids = group_shape(config, key).ids
    cells = [
        _Cell(*cell, cell.choice.make(tracer), BandScores(config.score_space))
        for cell in config.cells(key.scene, key.trace)
    ]
    warmup = group_warmup(config.warmup_frames, cells, ids)
    true, seen = (held_start(f, warmup - config.warmup_frames, profile.period_ns) for f in (frames.true, frames.seen))
    return Group(key, profile, tracer, ids, cells, warmup, true, seen)


def truth_cameras(group: Group, config: EvalConfig) -> list[EyeCamera]:
    """The eye cameras of a group's scored frames: the views whose ground truths it is scored against."""
    return [_request(inp, group.profile, config).camera for inp in group.inputs if inp.frame >= group.warmup]


def run_group(
    group: Group, config: EvalConfig, truth_of: Callable[[EyeCamera], np.ndarray], tick=None, worker: str | None = None
) -> GroupResult:
    """Render a planned group, its cells frame by frame in turn, and score it against truth_of's images; tick()
    after each cell's frame. `worker` (the Dask worker's address; None: in-process) goes into every row, as do
    the date, the commit and the machine of the process that rendered it (provenance.stamp)."""
    started = time.perf_counter()
    requests = _shown(group, config)
    last, scored = _render(group, config, requests, truth_of, tick or (lambda: None))
    for _ in range(config.timing_rounds - 1):
        _time_round(group, requests, tick or (lambda: None))
    jod = _jod(group.cells, scored, JodScorer(group.profile, config.eye)) if config.jod else {}
    seconds = round(time.perf_counter() - started, 3)
    true, seen = group.inputs[group.warmup :], group.seen[group.warmup :]
    errors = gaze.gaze_errors_deg(true, seen, config.eye)
    columns = {
        **gaze.gaze_columns(group.key.trace, errors),
        **gaze.pose_columns(group.key.trace, gaze.pose_errors_deg(true, seen)),
    }
    rows = _rows(group.ids, group.cells, group.profile, group.warmup, config.score_space)
    rows = [
        {
            **row,
            "trace_group": group.key.trace.group_label,
            **jod.get(row["label"], {}),
            **columns,
            "gaze_outside_fovea": gaze.outside_fovea(errors, gaze.foveal_radius_deg(cell.choice)),
        }
        for row, cell in zip(rows, group.cells, strict=True)
    ]
    rows = [{**row, "worker": worker, "group_seconds": seconds, **provenance.stamp()} for row in rows]
    return GroupResult(rows, Crops(**group.ids, **last, images={c.label: c.last for c in group.cells}))


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


def _request(inp: FrameInput, profile: HmdProfile, config: EvalConfig) -> FrameRequest:
    [request] = frame_requests(inp, eye_cameras(profile, inp.pose, (config.eye,)), config.seed)
    return request


def _shown(group: Group, config: EvalConfig) -> list[tuple[FrameRequest, FrameRequest]]:
    """Each frame's request as scored (the true gaze and pose) and as rendered (the tracked gaze and pose)."""
    out = []
    for inp, seen in zip(group.inputs, group.seen, strict=True):
        request = _request(inp, group.profile, config)
        camera = eye_cameras(group.profile, seen.pose, (config.eye,))[config.eye]
        out.append((request, dataclasses.replace(request, camera=camera, gaze=seen.gaze[config.eye])))
    return out


def _timed(method: Method, request: FrameRequest, stats: FrameStats) -> tuple[np.ndarray, float, float]:
    """The method's image of `request`, its wall ms and the process's CPU ms (every tracing thread's) in it."""
    wall, cpu = time.perf_counter_ns(), time.process_time_ns()
    image = method.render(request, stats)
    return image, (time.perf_counter_ns() - wall) * 1e-6, (time.process_time_ns() - cpu) * 1e-6


def _render(
    group: Group, config: EvalConfig, requests: list[tuple[FrameRequest, FrameRequest]], truth_of, tick
) -> tuple[dict, dict]:
    """Each input frame through every cell's method in turn; the frames after the warm-up timed and scored (the
    first timing round). Returns the last scored frame's truth and gaze pixel, and (with jod) every scored truth,
    encoded, and gaze."""
    last: dict = {}
    truths, gazes = [], []
    for cell in group.cells:
        cell.ms.append([])
        cell.cpu_ms.append([])
    for inp, (request, shown) in zip(group.inputs, requests, strict=True):
        scored = inp.frame >= group.warmup
        if scored:
            truth = truth_of(request.camera)
            eccentricity = eccentricity_map(request.camera, request.gaze)
            last = {"truth": truth, "gaze_xy": tuple(float(v) for v in request.camera.gaze_pixel(request.gaze))}
            if config.jod:
                truths.append(encode(truth))
                gazes.append(last["gaze_xy"])
        for cell in group.cells:
            if not scored and not cell.method.warmup_frames:
                tick()  # no history: nothing to warm up
                continue
            stats = FrameStats()
            image, ms, cpu_ms = _timed(cell.method, shown, stats)
            if scored:
                pixels = image.shape[0] * image.shape[1]
                cell.ms[-1].append(ms)
                cell.cpu_ms[-1].append(cpu_ms)
                cell.rays.append(sum(stats.rays.values()))
                for kind, n in stats.rays.items():
                    cell.rays_by_kind[kind] += n
                cell.fractions.append(stats.metrics.get("sample_fraction", stats.rays["primary"] / pixels))
                for name, value in stats.metrics.items():
                    if isinstance(value, numbers.Real) and math.isfinite(value):
                        cell.metrics.setdefault(name, []).append(float(value))
                cell.scores.add(image, truth, eccentricity)
                cell.last = image.copy()
                if config.jod:
                    cell.frames.append(encode(image))
                for stage, stage_ms in stats.stages_ms.items():
                    if "/" not in stage:
                        cell.stages_ms[stage] = cell.stages_ms.get(stage, 0.0) + stage_ms
            tick()
    return last, {"truths": truths, "gazes": gazes}


def _time_round(group: Group, requests: list[tuple[FrameRequest, FrameRequest]], tick) -> None:
    """One more timing round: every cell's method afresh through the warm-up and the scored frames, frame by frame
    in turn as in _render, the scored frames timed into a new round of the cell's times and not scored."""
    methods = [cell.choice.make(group.tracer) for cell in group.cells]
    for cell in group.cells:
        cell.ms.append([])
        cell.cpu_ms.append([])
    for inp, (_, shown) in zip(group.inputs, requests, strict=True):
        scored = inp.frame >= group.warmup
        for cell, method in zip(group.cells, methods, strict=True):
            if scored or method.warmup_frames:
                _, ms, cpu_ms = _timed(method, shown, FrameStats())
                if scored:
                    cell.ms[-1].append(ms)
                    cell.cpu_ms[-1].append(cpu_ms)
            tick()


def _rows(group: dict, cells: list[_Cell], profile, warmup: int, space: ScoreSpace) -> list[dict]:
    rows = []
    for cell in cells:
        frames = len(cell.ms[0])
        rows.append(
            {
                **group,
                "width": profile.width,
                "height": profile.height,
                "method": cell.choice.name,
                "params": str(cell.choice),
                "options": msgspec.to_builtins(cell.choice.params),
                "label": cell.label,
                "frames": frames,
                "warmup_frames": warmup if cell.method.warmup_frames else 0,
                "timing_rounds": len(cell.ms),
                "ms_per_frame": round(statistics.median(_means(cell.ms)), 3),
                "cpu_ms_per_frame": round(statistics.median(_means(cell.cpu_ms)), 3),
                "rays_per_frame": round(float(np.mean(cell.rays))),
                **{f"rays_{k}": round(n / frames) for k, n in cell.rays_by_kind.items()},
                "sample_fraction": round(float(np.mean(cell.fractions)), 5),
                "metrics": {k: round(statistics.fmean(v), 5) for k, v in cell.metrics.items()},
                "score_space": space,
                **{k: _round(v) for k, v in cell.scores.result().items()},
                "stages_ms": {k: round(v / frames, 3) for k, v in cell.stages_ms.items()},
            }
        )
    by_label = {cell.label: cell for cell in cells}
    full = next((r for r in rows if r["method"] == "full"), None)
    for row, cell in zip(rows, cells, strict=True):
        row["speedup_vs_full"] = round(full["ms_per_frame"] / row["ms_per_frame"], 3) if full else None
        baseline = next((r for r in rows if r["label"] == cell.compare_to), None) if cell.compare_to else full
        row.update(_comparison(row, baseline))
        row.update(_spread(cell, by_label[baseline["label"]] if baseline else None))
    front = pareto_front([(r["ms_per_frame"], r["psnr_fovea"]) for r in rows])
    for row, on in zip(rows, front, strict=True):
        row["pareto"] = on
    return rows


def _means(rounds: list[list[float]]) -> list[float]:
    return [statistics.fmean(times) for times in rounds]


def _spread(cell: _Cell, baseline: _Cell | None) -> dict:
    """How far the cell's speed-up over its baseline moves from round to round: the range of the per-round ratios
    over their median (None with one round or no baseline), and whether that exceeds NOISY_SPREAD."""
    if baseline is None or len(cell.ms) < 2:
        return {"speedup_spread": None, "timing_noisy": False}
    ratios = [b / c for b, c in zip(_means(baseline.ms), _means(cell.ms), strict=True)]
    spread = (max(ratios) - min(ratios)) / statistics.median(ratios)
    return {"speedup_spread": round(spread, 4), "timing_noisy": spread > NOISY_SPREAD}


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
    PSNR is at least the baseline's (the speed-up criterion: at least full's PSNR), with its speed-up and PSNR delta."""
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
    noisy = [r["label"] for r in candidates if r.get("timing_noisy")]  # rows of one timing round may lack it
    candidates = [r for r in candidates if not r.get("timing_noisy")]
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
        "noisy": noisy,  # cells that reach the baseline's foveal PSNR but whose speed-up is noisy: left out
    }
