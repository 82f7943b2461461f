"""The config of `hmdrt eval CONFIG.toml`: scenes, profiles, gaze and pose traces, and methods with parameter
sweeps; every cell of their product is rendered and scored. Paths are relative to the config file.
"""

from __future__ import annotations

import collections
import itertools
import math
import os
from pathlib import Path
from typing import Annotated, Literal, NamedTuple

import msgspec

from hmdrt.errors import ConfigError
from hmdrt.evaluate import perceptual
from hmdrt.evaluate.gaze import check_rates
from hmdrt.evaluate.groups import check_work
from hmdrt.evaluate.quality import ScoreSpace
from hmdrt.files.configfile import convert, read_toml
from hmdrt.foveation import MethodChoice
from hmdrt.spatial import parse_gaze
from hmdrt.tracking.model import Tracker
from hmdrt.tracking.pose import PoseTracker, pose_tracker_named
from hmdrt.tracking.presets import tracker_named

Scalar = str | int | float | bool
Option = Scalar | list[Scalar]  # a list: an option of several values (kim21's alpha at its six band edges)
MAX_CELLS = 10_000  # method cells of one sweep: checked before any is built
MAX_LISTED = 8  # labels an error message lists
MAX_LATENCY_MS = 1000.0  # beyond a second a tracker is not driving a fovea


class _Table(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    pass


class Trace(_Table):
    """What the eye and head do: a fixed gaze with the head still, a recorded trace, or the built-in path
    (head sway with fixations and saccades). Exactly one of gaze, path, builtin.

    The method sees the gaze as an eye tracker reports it (a preset name or a Tracker table: hmdrt.tracking.model)
    latency_ms late, and the head pose as a head tracker reports it (a preset name or a PoseTracker table:
    hmdrt.tracking.pose) pose_latency_ms late, both held or predicted as the compositor's SampleStore does
    (prediction "default": the run config's [prediction] defaults; "saccade": those and [gaze] saccade_prediction,
    hmdrt.tracking.saccade); the scores follow the true gaze, against
    truths rendered at the true pose. The defaults, perfect trackers without latency or prediction, give the
    method the true gaze and pose. A sweep gives some of those keys several values: the entry stands for one trace
    per combination (the latency table's 0-150 ms with two trackers and three predictions is one entry)."""

    name: str = ""
    gaze: str = ""  # "YAW,PITCH" in degrees
    path: str = ""  # a gaze/pose trace (JSONL, CSV, EyeLink ASC)
    builtin: bool = False
    # traces of one group are averaged in the papers' tables (smith2013 section 4: one frame for every fovea
    # position); "": the trace is its own group
    group: str = ""
    latency_ms: Annotated[float, msgspec.Meta(ge=0.0, le=MAX_LATENCY_MS)] = 0.0  # sample to photon
    tracker: str | Tracker = "perfect"
    pose_latency_ms: Annotated[float, msgspec.Meta(ge=0.0, le=MAX_LATENCY_MS)] = 0.0  # sample to photon
    pose_tracker: str | PoseTracker = "perfect"
    prediction: Literal["off", "default", "saccade"] = "off"  # the gaze's and the pose's alike, as in the compositor
    sweep: dict[Literal["latency_ms", "tracker", "pose_latency_ms", "pose_tracker", "prediction"], list[Scalar]] = {}

    def __post_init__(self) -> None:
        if self.sweep:
            count = math.prod(len(values) for values in self.sweep.values())
            if count > MAX_CELLS:
                raise ValueError(f"its sweep makes {count} traces, more than {MAX_CELLS}")
            self.expanded()  # every combination valid: a bad value fails here, naming the key
        if sum((bool(self.gaze), bool(self.path), self.builtin)) != 1:
            raise ValueError("a trace needs exactly one of gaze, path or builtin = true")
        if self.gaze:
            try:
                parse_gaze(self.gaze)
            except ConfigError as exc:
                raise ValueError(str(exc)) from None
        if isinstance(self.tracker, str):
            tracker_named(self.tracker)
        if isinstance(self.pose_tracker, str):
            pose_tracker_named(self.pose_tracker)

    def __hash__(self) -> int:
        """A hash of every field, the sweep's lists as tuples (a trace names a group: a key of dicts)."""
        fields = tuple(getattr(self, f) for f in self.__struct_fields__ if f != "sweep")
        return hash((*fields, tuple((k, tuple(v)) for k, v in self.sweep.items())))

    def expanded(self) -> list[Trace]:
        """The traces this entry stands for: itself, or one per combination of its sweep's values (a swept key
        overrides the entry's own); a ValueError naming the key and value for a value the key does not take."""
        if not self.sweep:
            return [self]
        fields = {k: v for k, v in msgspec.structs.asdict(self).items() if k != "sweep"}
        for key, values in self.sweep.items():
            for value in values:
                try:
                    msgspec.convert({**fields, key: value}, Trace)
                except msgspec.ValidationError as exc:
                    raise ValueError(f"sweep {key} {value!r}: {str(exc).partition(' - at ')[0]}") from None
        keys = list(self.sweep)
        combos = itertools.product(*(self.sweep[k] for k in keys))
        return [msgspec.convert({**fields, **dict(zip(keys, combo, strict=True))}, Trace) for combo in combos]

    @property
    def tracker_model(self) -> Tracker:
        """The eye tracker: the preset named, or the table given."""
        return tracker_named(self.tracker) if isinstance(self.tracker, str) else self.tracker

    @property
    def pose_tracker_model(self) -> PoseTracker:
        """The head tracker: the preset named, or the table given."""
        return pose_tracker_named(self.pose_tracker) if isinstance(self.pose_tracker, str) else self.pose_tracker

    @property
    def tracker_label(self) -> str:
        """The eye tracker as rows and labels name it (_model_label)."""
        return _model_label(self.tracker)

    @property
    def pose_tracker_label(self) -> str:
        """The head tracker as rows and labels name it (_model_label)."""
        return _model_label(self.pose_tracker)

    @property
    def source(self) -> str | None:
        """The trace as sequence_inputs takes it: a path, "builtin", or None for the fixed gaze."""
        return self.path or ("builtin" if self.builtin else None)

    @property
    def label(self) -> str:
        """The name, else what the trace is, with its latency, tracker, pose latency and pose tracker ("pose 20 ms
        htc-vive") and prediction where not the defaults."""
        if self.name:
            return self.name
        parts = [f"gaze {self.gaze}" if self.gaze else Path(self.path).stem if self.path else "builtin"]
        parts += _tracked(self.latency_ms, self.tracker_label)
        if self.pose_latency_ms or self.pose_tracker_label != "perfect":
            parts += ["pose", *_tracked(self.pose_latency_ms, self.pose_tracker_label)]
        parts += [f"prediction {self.prediction}"] if self.prediction != "off" else []
        return " ".join(parts)

    @property
    def group_label(self) -> str:
        return self.group or self.label

    def named(self, names: list[str]) -> bool:
        """Whether `names` selects this trace, by its label or its group ([]: every trace)."""
        return not names or self.label in names or self.group_label in names


def _model_label(model: str | Tracker | PoseTracker) -> str:
    """A tracker preset's name, or a table's fields that differ from a perfect tracker's ("perfect" if none)."""
    if isinstance(model, str):
        return model
    perfect = type(model)()
    fields = ((f, getattr(model, f)) for f in model.__struct_fields__)
    return "&".join(f"{f}={v:g}" for f, v in fields if v != getattr(perfect, f)) or "perfect"


def _tracked(latency_ms: float, tracker: str) -> list[str]:
    """A trace label's words for a latency and a tracker, each where not the default."""
    return ([f"{latency_ms:g} ms"] if latency_ms else []) + ([tracker] if tracker != "perfect" else [])


class Cell(NamedTuple):
    """One method setting of the eval: its choice, its label in tables and plots, and the label of the cell its
    speed-up and PSNR delta are measured against ("": the group's full)."""

    choice: MethodChoice
    label: str
    compare_to: str = ""


class MethodSweep(_Table):
    """A method with fixed options and a sweep: one cell per combination of the sweep's values. A label names
    the cell in tables and plots (a sweep's cells add their values to it); compare_to names the cell each of
    them is compared with (a paper's baseline: kim2021 measures Sel_Fov against Selective), full by default."""

    name: str
    options: dict[str, Option] = {}
    sweep: dict[str, list[Option]] = {}
    label: str = ""
    scenes: list[str] = []  # only on these of the config's scenes ([]: on all)
    traces: list[str] = []  # only on these of the config's traces, by label or group ([]: on all)
    compare_to: str = ""  # the label of another cell ("": full)

    def __post_init__(self) -> None:
        count = math.prod(len(values) for values in self.sweep.values())
        if count > MAX_CELLS:
            raise ValueError(f"method {self.name!r}: its sweep makes {count} cells, more than {MAX_CELLS}")

    def cells(self) -> list[Cell]:
        """Each cell of the sweep; ConfigError for a bad name or value."""
        keys = list(self.sweep)
        combos = itertools.product(*(self.sweep[k] for k in keys)) if keys else [()]
        out = []
        for combo in combos:
            swept = dict(zip(keys, combo, strict=True))
            choice = MethodChoice.parse(self.name, **{**self.options, **swept})  # a swept key overrides its option
            label = " ".join([self.label, *(f"{k}={v}" for k, v in swept.items())]) if self.label else str(choice)
            out.append(Cell(choice, label, self.compare_to))
        return out


def default_cache_dir() -> str:
    return str(Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "hmdrt" / "truth")


class EvalConfig(_Table):
    scenes: list[str] = msgspec.field(default_factory=lambda: ["whitted"])
    profiles: list[str] = msgspec.field(default_factory=lambda: ["sim-cpu"])
    resolution: str = ""  # per-eye WIDTHxHEIGHT overriding every profile's, same field of view
    eye: Literal["left", "right"] = "left"
    frames: Annotated[int, msgspec.Meta(ge=1, le=100_000)] = 8  # per cell
    warmup_frames: Annotated[int, msgspec.Meta(ge=0, le=100_000)] = 2  # rendered, neither timed nor scored
    # the frames rendered again this many times in all, from fresh methods, for their times (hmdrt.evaluate.runner)
    timing_rounds: Annotated[int, msgspec.Meta(ge=1, le=100)] = 3
    truth_spp: Annotated[int, msgspec.Meta(ge=1, le=1024)] = 36  # the ground truth: regular at this many spp
    seed: int = 0
    threads: Annotated[int, msgspec.Meta(ge=0, le=256)] = 0  # tracing threads (0: all cores)
    cache_dir: str = ""  # ground truths are cached here ("": $XDG_CACHE_HOME/hmdrt/truth)
    jod: bool = False  # FovVideoVDP's foveated JOD per cell (needs the eval extra)
    tables: list[Literal["weier2016", "kim2021", "smith2013", "weier2018", "latency"]] = []  # tables.md
    crop_px: Annotated[int, msgspec.Meta(ge=8, le=4096)] = 96  # side of the crops at the gaze point
    score_space: ScoreSpace = "srgb"  # PSNR, SSIM and flicker of display-encoded images, or of linear radiance
    traces: list[Trace] = msgspec.field(default_factory=lambda: [Trace(gaze="0,0")])
    methods: list[MethodSweep] = msgspec.field(default_factory=lambda: [MethodSweep("full"), MethodSweep("rrm")])
    source: str = ""

    def __post_init__(self) -> None:
        msgspec.structs.force_setattr(self, "traces", [t for entry in self.traces for t in entry.expanded()])
        if self.warmup_frames >= self.frames:
            raise ValueError(f"warmup_frames ({self.warmup_frames}) must be fewer than frames ({self.frames})")
        if not (self.scenes and self.profiles and self.traces and self.methods):
            raise ValueError("scenes, profiles, traces and methods each need at least one entry")
        traces = {t.label for t in self.traces} | {t.group_label for t in self.traces}
        for m in self.methods:
            if unknown := set(m.scenes) - set(self.scenes):
                raise ValueError(f"method {m.name!r} names scenes not in scenes: {', '.join(sorted(unknown))}")
            if unknown := set(m.traces) - traces:
                raise ValueError(f"method {m.name!r} names traces not in traces: {', '.join(sorted(unknown))}")

    def cells(self, scene: str | None = None, trace: Trace | None = None) -> list[Cell]:
        """Every method cell (on `scene` and `trace`; None: on any) in config order, a repeated choice kept where it
        first is."""
        found: dict[MethodChoice, Cell] = {}
        for m in self.methods:
            if (scene is None or not m.scenes or scene in m.scenes) and (trace is None or trace.named(m.traces)):
                for cell in m.cells():
                    found.setdefault(cell.choice, cell)
        return list(found.values())

    def check_baselines(self) -> None:
        """A ConfigError unless each compare_to names exactly one cell on every scene and trace its method runs on."""
        if not any(m.compare_to for m in self.methods):
            return
        for scene, trace in itertools.product(self.scenes, self.traces):
            cells = self.cells(scene, trace)
            labels = collections.Counter(c.label for c in cells)
            for cell in cells:
                if cell.compare_to and labels[cell.compare_to] != 1:
                    raise ConfigError(_baseline_error(cell, f"{scene!r}, trace {trace.label!r}", labels))


def load_eval_config(path: str | Path, **overrides) -> EvalConfig:
    """A validated EvalConfig from a TOML file, with its trace paths and cache folder resolved against the file;
    every method spec is checked before anything is rendered."""
    data = read_toml(path)
    data.update({k: v for k, v in overrides.items() if v is not None})
    config = convert(data, EvalConfig, path)
    check_work(config)  # sizes that cannot fit, before anything is built
    base = Path(path).resolve().parent
    traces = [
        msgspec.structs.replace(t, path=str(base / t.path)) if t.path and not Path(t.path).is_absolute() else t
        for t in config.traces
    ]
    cache = str(base / config.cache_dir) if config.cache_dir else default_cache_dir()
    config.cells()  # every method choice parsed: a bad one fails here
    config.check_baselines()
    check_rates(traces, path)  # a recording too slow for its trackers
    if config.jod:
        perceptual.require()
    return msgspec.structs.replace(config, traces=traces, cache_dir=cache, source=str(path))


def _baseline_error(cell: Cell, where: str, labels: collections.Counter[str]) -> str:
    """Why a cell's compare_to does not name one cell of the scene, listing some of the labels there."""
    count = labels[cell.compare_to]
    more = ", ..." if len(labels) > MAX_LISTED else ""
    listed = ", ".join(repr(label) for label in list(labels)[:MAX_LISTED]) + more
    found = f"names {count} cells" if count else f"names no cell (labels there: {listed})"
    return f"method {cell.choice.name!r} ({cell.label!r}): compare_to {cell.compare_to!r} {found} on scene {where}"
