"""The "hold-budget" controller: trades a method's quality for time so that deadline misses stay under a
configured rate, and widens the fovea for gaze speed and tracker error.

The compositor calls update() once per presented frame (and, with foresight, anticipate() before each frame).
One quality level in [0, 1] drives the method's cost knobs (Method.knobs, each method's own declaration): 1 is
the parameters the method was configured with, 0 a floor from the papers, and each knob moves linearly between
the two (integer knobs rounded), so every knob is monotonic in the level and one number tells the story in the
run report. A floor never asks
for more than the configured value: a knob configured below its floor stays where it is. A method without
knobs (full, regular) is left alone, and the trajectory says so.

Feedback's control law, with r = render time / (headroom x budget) per frame:
- after a level change, wait settle_frames frames (temporal methods need them to settle); then
- a miss while more than target_miss_rate of the last miss_window frames missed: lower the level by
  max(miss_step, gain (mean r - aim)), mean r over the last settle_frames frames;
- else mean r above 1: lower it by max(min_step, gain (mean r - aim));
- else mean r over the last raise_after frames below raise_below and none of them missed: raise it by
  up_step. Between raise_below and 1 the level holds, so it does not hunt; a drop aims at the middle of
  that band, aim = (1 + raise_below) / 2, so that render-time noise does not push it out again.
At level 0 the controller can do no more: at_floor is set and the compositor reports the rate achieved.

Foresight (foresight on: the run config's default): feedback learns of a costly frame only once it has missed, and
the frame that misses is the one whose fovea has just landed on costly content (a saccade onto glass). So before
each frame is rendered, anticipate() takes a probe's reading of the fovea where the gaze is about to be and the
cost model's prediction of the frame at every level (hmdrt.compositor.foresight), and renders the frame at the
highest level predicted within `fit` x headroom x budget, else at level 0; update() then teaches the model the
frame's time and rays instead of stepping the level. The level comes back as soon as the fovea is back on cheaper
content. A miss while misses exceed target_miss_rate tightens the fit by miss_step (to half foresight_fit), and
raise_after frames without one ease it back by up_step, up to foresight_fit. A method without a foveal knob has no
fovea to probe: its controller acts by feedback.

Foveal widening: each foveal radius knob (Knob.foveal) is its level value + gaze speed x widen_latency_ms +
accuracy_deg, clamped to the field's valid range, so the fovea still covers where the eye is when the frame
is shown, as far as the tracker knows. The widening rounds up to widen_step_deg, grows at once and shrinks
only once it has not grown for settle_frames frames: every change can cost the method a rebuild (weier18
redraws its sampling tables).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from itertools import islice
from typing import NamedTuple

import msgspec

from hmdrt.compositor.config import RunConfig
from hmdrt.compositor.foresight import GRID, CostModel, Foresight
from hmdrt.errors import ConfigError
from hmdrt.foveation.base import Method

FORESEEN = 8  # frames anticipated and not yet learnt of, kept: a frame is learnt of a VSync or two after it is rendered
# trajectory entries kept after the start, the newest: the `stats` topic sends them every second, and a daemon
# runs for hours; `changes` counts them all, and every frame record carries the knobs it was rendered with
LOGGED = 100


@dataclass(frozen=True)
class ControllerConfig:
    """The hold-budget controller's settings; the module docstring says how each acts."""

    target_miss_rate: float = 0.05  # misses allowed (fraction of frames)
    headroom: float = 0.85  # aim render time at this fraction of the render budget
    widen_latency_ms: float = 0.0  # tracker latency to cover: fovea widened by gaze speed * this
    accuracy_deg: float = 0.0  # tracker accuracy to cover: fovea widened by this
    settle_frames: int = 6  # frames after a level change before the next decision
    miss_window: int = 60  # frames over which the miss rate is compared with target_miss_rate
    raise_after: int = 30  # frames well below target, none missed, before the level rises
    raise_below: float = 0.8  # "well below": mean render time under this fraction of the target
    gain: float = 1.0  # level dropped per unit of mean r above the aim
    min_step: float = 0.02  # smallest drop
    miss_step: float = 0.1  # smallest drop on a miss over the allowed rate
    up_step: float = 0.05  # one rise
    widen_step_deg: float = 0.5  # the widening rounds up to a multiple of this (0: exact)
    adjust_level: bool = True  # False: the level stays at 1 and only the widening acts (no controller configured)
    foresight: bool = False  # pick each frame's level from its predicted render time (anticipate), not feedback
    foresight_fit: float = 0.85  # foresight renders within this fraction of headroom x budget, as predicted

    def __post_init__(self) -> None:
        checks = {
            "target_miss_rate": 0.0 <= self.target_miss_rate <= 1.0,
            "headroom": 0.0 < self.headroom <= 1.0,
            "widen_latency_ms": self.widen_latency_ms >= 0.0,
            "accuracy_deg": self.accuracy_deg >= 0.0,
            "settle_frames": self.settle_frames >= 1,
            "miss_window": self.miss_window >= 1,
            "raise_after": self.raise_after >= self.settle_frames,
            "raise_below": 0.0 < self.raise_below < 1.0,
            "gain": self.gain >= 0.0,
            "min_step": 0.0 < self.min_step <= 1.0,
            "miss_step": 0.0 < self.miss_step <= 1.0,
            "up_step": 0.0 < self.up_step <= 1.0,
            "widen_step_deg": self.widen_step_deg >= 0.0,
            "foresight_fit": 0.0 < self.foresight_fit <= 1.0,
        }
        bad = [f"{name}={getattr(self, name)}" for name, ok in checks.items() if not ok]
        if bad:
            raise ConfigError(f"controller settings out of range: {', '.join(bad)}")


class _Span(NamedTuple):
    """One knob resolved for the configured parameters: its values at level 1 and 0 and its valid range."""

    field: str
    top: float
    bottom: float
    lo: float
    hi: float
    integer: bool
    foveal: bool

    def at(self, level: float, widen_deg: float) -> float:
        value = self.bottom + level * (self.top - self.bottom) + (widen_deg if self.foveal else 0.0)
        value = min(max(value, self.lo), self.hi)
        return math.floor(value + 0.5) if self.integer else value


def field_range(params_type: type[msgspec.Struct], name: str) -> tuple[float, float, bool]:
    """The bounds a Params field's constraints allow (inclusive or not) and whether it is an integer."""
    field = next(f for f in msgspec.inspect.type_info(params_type).fields if f.name == name)
    kind = field.type
    if isinstance(kind, msgspec.inspect.UnionType):  # an optional field: its number type
        kind = next(t for t in kind.types if not isinstance(t, msgspec.inspect.NoneType))
    lo = next((b for b in (kind.ge, kind.gt) if b is not None), -math.inf)
    hi = next((b for b in (kind.le, kind.lt) if b is not None), math.inf)
    return lo, hi, isinstance(kind, msgspec.inspect.IntType)


def spans(method: type[Method] | Method, params: msgspec.Struct) -> tuple[_Span, ...]:
    """The method's knobs resolved for `params`."""
    values = method.knob_values(params)
    out = []
    for knob in method.knobs:
        lo, hi, integer = field_range(type(params), knob.field)
        top = min(max(values[knob.field], lo), hi)  # frc=full's infinite radii: the largest valid ones
        floor = knob.floor(values) if callable(knob.floor) else knob.floor
        bottom = top if floor is None else (min if knob.cheaper == "lower" else max)(top, floor)
        out.append(_Span(knob.field, top, bottom, lo, hi, integer, knob.foveal))
    return tuple(out)


class BudgetController:
    """Holds a method's deadline misses under a rate by moving its cost knobs (module docstring).

    Build a new one whenever the method or its parameters are changed from outside: level 1 is the
    parameters the method had when the controller was made.
    """

    def __init__(self, method: Method, config: ControllerConfig):
        self.method = method
        self.config = config
        self.base = method.params
        self._spans = spans(method, self.base)
        self.knobs = tuple(s.field for s in self._spans)
        self._level = 1.0
        self._ratios: deque[float] = deque(maxlen=config.raise_after)
        self._misses: deque[bool] = deque(maxlen=max(config.miss_window, config.raise_after))
        self._since_change = 0
        self._since_grow = 0
        self.widen_deg = 0.0
        self.widenings = 0  # knob changes made by the widening alone (not in the trajectory)
        self._configured = self._values(1.0, 0.0)
        self._applied = self._configured
        self._refused: dict[str, float] | None = None
        reason = "start" if self._spans else f"{method.name} has no cost knobs: nothing to tune"
        self.trajectory: list[dict] = [self._entry(None, reason)]
        self.changes = 0  # trajectory entries after the start, also those no longer kept
        # frame -> its level and foveal radius, the probe's reading, whether its level changed
        self._foreseen: dict[int, tuple[float, float, Foresight, bool]] = {}
        self.model = CostModel()
        self.fit = config.foresight_fit  # what anticipate() renders within; tightened by misses over the target
        self._budget_ns = 0
        self._calm = 0  # frames since the last miss or easing of the fit

    @property
    def foresees(self) -> bool:
        """Whether anticipate() can act: foresight on, the level adjusted, and a foveal knob to probe around."""
        return self.config.foresight and self.config.adjust_level and self.fovea_deg is not None

    @property
    def fovea_deg(self) -> float | None:
        """The applied value of the method's first foveal knob (its foveal radius), None without one."""
        return next((self._applied[s.field] for s in self._spans if s.foveal), None)

    @property
    def level(self) -> float:
        """1.0: the method's own parameters (best quality); 0.0: the knob floor."""
        return self._level

    @property
    def at_floor(self) -> bool:
        """Whether the controller cannot lower the cost any further (level 0, or no knobs at all)."""
        return not self._spans or self._level <= 0.0

    def update(
        self,
        frame_id: int,
        render_ns: int,
        budget_ns: int,
        missed: bool,
        gaze_speed_deg_s: float | None = None,
        extra_widen_deg: float = 0.0,
        rays: int = 0,
    ) -> dict[str, float] | None:
        """Take one presented frame's render time against its budget; the knob values applied from the
        next frame on, or None when they stay. gaze_speed_deg_s None (or not finite): unknown, no widening
        for speed; extra_widen_deg widens the fovea further (a silent tracker, hmdrt.compositor.fallback);
        rays: the frame's rays, for foresight. The trajectory lists every level change and refusal (frame,
        level, knobs, reason)."""
        if not self._spans:
            return None
        if budget_ns <= 0:
            raise ValueError(f"budget_ns must be positive, got {budget_ns}")
        self._ratios.append(render_ns / (self.config.headroom * budget_ns))
        self._misses.append(missed)
        self._since_change += 1
        self._budget_ns = budget_ns
        widen = self._widening(gaze_speed_deg_s, extra_widen_deg)
        if self.foresees:
            foreseen = self._foreseen.pop(frame_id, None)
            if foreseen is not None:
                self.model.learn(foreseen[0], foreseen[1], render_ns, rays, foreseen[2], foreseen[3])
            self._tighten(missed)
            return self._move(frame_id, self._level, "", widen)
        step, reason = self._decide(missed)
        return self._move(frame_id, self._level + step, reason, widen)

    def anticipate(self, frame_id: int, fore: Foresight) -> dict[str, float] | None:
        """Before frame `frame_id` is rendered, what the probe read of its fovea: the highest level of the grid whose
        predicted render time (with what a change costs, for a level other than the held one) is within `fit` of the
        target, else level 0 (module docstring, "Foresight"); the knob values it is rendered with when they
        change, else None."""
        if not self.foresees:
            return None
        held, level, reason = self._level, self._level, ""
        ahead = self._ahead(fore) if self._budget_ns else {}
        if ahead:
            target = self.fit * self.config.headroom * self._budget_ns
            fits = [at for at, ns in ahead.items() if ns <= target]
            level = max(fits) if fits else 0.0  # the knobs are monotonic: the floor is the cheapest
            reason = f"foresight: {ahead[level] / 1e6:.1f} ms ahead at this level"
        values = self._move(frame_id, level, reason, self.widen_deg)
        self._foreseen[frame_id] = (self._level, self.fovea_deg, fore, self._level != held)
        while len(self._foreseen) > FORESEEN:
            del self._foreseen[next(iter(self._foreseen))]
        return values

    def _ahead(self, fore: Foresight) -> dict[float, float]:
        """Each level of the grid's predicted render time (ns), a change's cost added to every level but the held one;
        empty before the model has learnt a frame."""
        radius = next(s for s in self._spans if s.foveal)
        change = self.model.change_ns
        ahead = {}
        for i in range(GRID + 1):
            at = i / GRID
            ns = self.model.predict(at, fore, radius.at(at, self.widen_deg))
            if math.isnan(ns):
                return {}
            ahead[at] = ns + (0.0 if at == self._level else change)
        return ahead

    def _tighten(self, missed: bool) -> None:
        """Foresight's fit: tightened by miss_step on a miss while misses exceed the target rate (to half of
        foresight_fit at most), eased back by up_step after raise_after frames without one."""
        c = self.config
        window = list(islice(reversed(self._misses), c.miss_window))
        if missed and sum(window) / len(window) > c.target_miss_rate:
            self.fit, self._calm = max(self.fit - c.miss_step, c.foresight_fit / 2), 0
        elif self._calm >= c.raise_after and self.fit < c.foresight_fit:
            self.fit, self._calm = min(self.fit + c.up_step, c.foresight_fit), 0
        self._calm = 0 if missed else self._calm + 1

    def _move(self, frame_id: int, level: float, reason: str, widen: float) -> dict[str, float] | None:
        """Apply `level` (clamped to [0, 1]) and the widening: the knob values when they change, else None."""
        level = min(max(level, 0.0), 1.0)
        values = self._values(level, widen)
        if values == self._refused:
            return None  # neither the level nor the widening is taken while the method refuses its knobs
        if values != self._applied:
            try:
                self.method.set_params(self._params(values))
            except (msgspec.ValidationError, ConfigError, ValueError) as exc:
                self._refused = values
                self._log(frame_id, f"refused {values}: {exc}")
                return None
            self._applied = values
        else:
            values = None
        if level != self._level:
            self._level, self._since_change = level, 0
            self._log(frame_id, reason + (" (floor)" if level <= 0.0 else ""))
        elif values is not None:
            self.widenings += 1
        return values

    def _decide(self, missed: bool) -> tuple[float, str]:
        """The level step this frame calls for and why (0 and "" for none)."""
        c = self.config
        if not c.adjust_level or self._since_change < c.settle_frames:
            return 0.0, ""
        recent = _mean(islice(reversed(self._ratios), c.settle_frames))
        over = c.gain * (recent - 0.5 * (1.0 + c.raise_below))
        window = list(islice(reversed(self._misses), c.miss_window))
        miss_rate = sum(window) / len(window)
        if missed and miss_rate > c.target_miss_rate:
            return -max(c.miss_step, over), f"miss: {sum(window)} of the last {len(window)} frames missed"
        if recent > 1.0:
            return -max(c.min_step, over), f"over target: render {recent:.2f} x target"
        if self._since_change >= c.raise_after:
            calm = _mean(self._ratios)
            if calm < c.raise_below and not any(islice(reversed(self._misses), c.raise_after)):
                return c.up_step, f"under target: render {calm:.2f} x target"
        return 0.0, ""

    def _widening(self, gaze_speed_deg_s: float | None, extra_deg: float = 0.0) -> float:
        """The foveal widening for this gaze speed (and extra_deg), grown at once and shrunk after settle_frames."""
        c = self.config
        speed = gaze_speed_deg_s if gaze_speed_deg_s is not None and math.isfinite(gaze_speed_deg_s) else 0.0
        want = max(speed, 0.0) * c.widen_latency_ms / 1000.0 + c.accuracy_deg + max(extra_deg, 0.0)
        if c.widen_step_deg:
            want = math.ceil(want / c.widen_step_deg - 1e-9) * c.widen_step_deg
        self._since_grow += 1
        if want > self.widen_deg:
            self._since_grow = 0
        if want > self.widen_deg or self._since_grow >= c.settle_frames:
            self.widen_deg = want
        return self.widen_deg

    def _values(self, level: float, widen_deg: float) -> dict[str, float]:
        return {s.field: s.at(level, widen_deg) for s in self._spans}

    def _params(self, values: dict[str, float]) -> msgspec.Struct:
        """The configured parameters with `values`, validated by the Params struct; exactly the configured
        ones at level 1 without widening."""
        if values == self._configured:
            return self.base
        return msgspec.convert({**msgspec.structs.asdict(self.base), **values}, type(self.base))

    def _log(self, frame_id: int, reason: str) -> None:
        """A trajectory entry; beyond LOGGED after the start, the oldest goes."""
        self.trajectory.append(self._entry(frame_id, reason))
        self.changes += 1
        if len(self.trajectory) > LOGGED + 1:
            del self.trajectory[1]

    def _entry(self, frame_id: int | None, reason: str) -> dict:
        return {
            "frame": frame_id,
            "level": round(self._level, 4),
            "knobs": {k: round(v, 4) for k, v in self._applied.items()},
            "widen_deg": self.widen_deg,
            "reason": reason,
        }


def make_controller(config: RunConfig, method: Method) -> BudgetController | None:
    """The [controller] section's controller of `method`; with kind "none", one that only widens the fovea while the
    gaze tracker is silent (when [fallback] widens at all), else none."""
    c = config.controller
    if c.kind == "none":
        if not config.fallback.widen_deg_per_s:
            return None
        return BudgetController(method, ControllerConfig(adjust_level=False))
    settings = ControllerConfig(
        target_miss_rate=c.target_miss_rate,
        headroom=c.headroom,
        widen_latency_ms=c.widen_latency_ms,
        accuracy_deg=c.accuracy_deg,
        foresight=c.foresight,
    )
    return BudgetController(method, settings)


def _mean(values) -> float:
    values = list(values)
    return sum(values) / len(values)
