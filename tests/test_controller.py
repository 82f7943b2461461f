"""The hold-budget controller on real methods and synthetic frame times: settings, the control law, floors,
recovery without hunting, foveal widening, and handing the configured parameters back at level 1."""

import math
from typing import Annotated

import msgspec
import numpy as np
import pytest

from hmdrt.compositor.controller import LOGGED, BudgetController, ControllerConfig, field_range, spans
from hmdrt.errors import ConfigError
from hmdrt.foveation import METHODS, make_method
from hmdrt.foveation.base import Configurable, Knob, NoParams, Stage
from hmdrt.foveation.kim21 import Kim21, Kim21Params
from hmdrt.foveation.rrm import Rrm, RrmParams
from hmdrt.foveation.weier16 import Weier16, Weier16Params
from hmdrt.foveation.weier18 import Weier18Params
from hmdrt.trace.integrator import Whitted

BUDGET_NS = 10_000_000
TUNABLE = [name for name, method in METHODS.items() if method.knobs]  # weier16, weier18, rrm, kim21
# headroom 0.5 makes the target 5 ms, so r = 1.25 is exact; with raise_below 0.5 (aim 0.75) and gain 0.5 a
# drop at r = 1.25 is exactly 0.25: the levels run 1, 0.75, 0.5, 0.25, 0
EXACT = {"headroom": 0.5, "raise_below": 0.5, "gain": 0.5}
# level 0 of each method with default parameters (group_h 4: group_w 5 makes N = 20)
FLOORS = {
    "weier16": {"r0": 5.0, "r1": 10.0, "p_min": 0.01},
    "weier18": {"r0": 5.0, "r1": 10.0, "p_min": 0.01},
    "rrm": {"fovea_deg": 5.0, "group_w": 5},
    "kim21": {
        "n_f": 1,
        "n_p": 1,
        "n_m": 1,
        "n_np": 1,
        "e_f": 3.3,
        "e_p": 5.5,
        "e_m": 12.1,
        "e_np": 30.0,
        "e_max": 45.0,
    },
}
FOVEAL = {
    "weier16": ("r0", "r1"),
    "weier18": ("r0", "r1"),
    "rrm": ("fovea_deg",),
    "kim21": ("e_f", "e_p", "e_m", "e_np", "e_max"),
}


@pytest.fixture(scope="module")
def tracer(whitted_scene):
    with Whitted(whitted_scene) as t:
        yield t


class Run:
    """A controller over a real method, fed one synthetic frame at a time; r is render time / target."""

    def __init__(self, tracer: Whitted, spec: str, **settings):
        self.method = make_method(spec, tracer)
        self.calls: list[msgspec.Struct] = []  # every Params handed to set_params, refused ones included
        original = self.method.set_params

        def set_params(params):
            self.calls.append(params)
            original(params)

        self.method.set_params = set_params
        self.ctl = BudgetController(self.method, ControllerConfig(**settings))
        self.frame = 0

    def feed(self, n: int, r: float, missed: bool = False, speed: float | None = None) -> list:
        """n frames at r; what update() returned for each."""
        out = []
        for _ in range(n):
            render_ns = round(r * self.ctl.config.headroom * BUDGET_NS)
            out.append(self.ctl.update(self.frame, render_ns, BUDGET_NS, missed, speed))
            self.frame += 1
        return out

    def changes(self) -> list[dict]:
        """The trajectory's level changes (no start, no refusals)."""
        return [e for e in self.ctl.trajectory[1:] if not e["reason"].startswith("refused")]

    def until_floor(self, r: float = 1.25, limit: int = 600) -> None:
        while not self.ctl.at_floor and self.frame < limit:
            self.feed(1, r)
        assert self.ctl.at_floor


# settings


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("target_miss_rate", -0.01),
        ("target_miss_rate", 1.5),
        ("headroom", 0.0),
        ("headroom", 1.01),
        ("widen_latency_ms", -1.0),
        ("accuracy_deg", -0.1),
        ("settle_frames", 0),
        ("miss_window", 0),
        ("raise_after", 5),  # below settle_frames (6)
        ("raise_below", 0.0),
        ("raise_below", 1.0),
        ("gain", -0.5),
        ("min_step", 0.0),
        ("min_step", 1.5),
        ("miss_step", 0.0),
        ("up_step", 0.0),
        ("up_step", 2.0),
        ("widen_step_deg", -0.5),
    ],
)
def test_a_setting_out_of_range_is_a_config_error_naming_it(field, value):
    with pytest.raises(ConfigError, match=f"{field}={value}"):
        ControllerConfig(**{field: value})


def test_every_bad_setting_is_named_at_once_and_the_edges_are_valid():
    with pytest.raises(ConfigError) as err:
        ControllerConfig(headroom=2.0, gain=-1.0, settle_frames=0)
    assert all(f in str(err.value) for f in ("headroom=2.0", "gain=-1.0", "settle_frames=0"))
    ControllerConfig()
    ControllerConfig(target_miss_rate=0.0, headroom=1.0, settle_frames=1, raise_after=1, gain=0.0, widen_step_deg=0.0)
    ControllerConfig(target_miss_rate=1.0, min_step=1.0, miss_step=1.0, up_step=1.0, settle_frames=30, raise_after=30)


# the level


@pytest.mark.parametrize("name", TUNABLE)
def test_it_starts_at_level_one_with_the_configured_parameters_and_holds_on_target(tracer, name):
    run = Run(tracer, name)
    base = run.method.params
    ctl = run.ctl
    assert ctl.base is base and ctl.level == 1.0 and not ctl.at_floor
    assert ctl.knobs == tuple(k.field for k in METHODS[name].knobs)
    assert ctl.trajectory == [
        {
            "frame": None,
            "level": 1.0,
            "knobs": {k: pytest.approx(v) for k, v in METHODS[name].knob_values(base).items() if k in ctl.knobs},
            "widen_deg": 0.0,
            "reason": "start",
        }
    ]
    assert run.feed(120, 0.9) == [None] * 120  # inside the band: nothing to do
    assert run.method.params is base and run.calls == [] and ctl.level == 1.0 and len(ctl.trajectory) == 1


def test_sustained_overload_lowers_the_level_step_by_step_after_settling(tracer):
    run = Run(tracer, "weier16", **EXACT)
    out = run.feed(30, 1.25)
    changed = [f for f, v in enumerate(out) if v is not None]
    assert changed == [5, 11, 17, 23]  # a decision every settle_frames frames, not before
    assert [e["level"] for e in run.changes()] == [0.75, 0.5, 0.25, 0.0]
    assert [e["frame"] for e in run.changes()] == changed
    expected = [(8.75, 17.5, 0.04), (7.5, 15.0, 0.03), (6.25, 12.5, 0.02), (5.0, 10.0, 0.01)]
    for f, (r0, r1, p_min) in zip(changed, expected, strict=True):
        assert out[f] == pytest.approx({"r0": r0, "r1": r1, "p_min": p_min})
    for entry, values in zip(run.changes(), [out[f] for f in changed], strict=True):
        assert set(entry) == {"frame", "level", "knobs", "widen_deg", "reason"}
        assert entry["knobs"] == pytest.approx(values)
        assert entry["reason"].startswith("over target: render 1.25 x target")
    assert run.changes()[-1]["reason"].endswith("(floor)")
    assert not any(e["reason"].endswith("(floor)") for e in run.changes()[:-1])
    # set_params was applied each time: the method renders with the level's values
    assert len(run.calls) == 4
    p = run.method.params
    assert isinstance(p, Weier16Params) and (p.r0, p.r1, p.p_min) == pytest.approx((5.0, 10.0, 0.01))
    assert p.foveal() == pytest.approx((5.0, 10.0, 0.01))
    assert run.ctl.at_floor and run.ctl.level == 0.0


@pytest.mark.parametrize("name", TUNABLE)
def test_every_knob_moves_monotonically_from_its_configured_value_to_its_floor(tracer, name):
    run = Run(tracer, name, min_step=0.05, gain=0.1)  # small steps: many intermediate levels
    configured = {k: v for k, v in run.method.knob_values(run.ctl.base).items() if k in run.ctl.knobs}
    run.until_floor(r=1.1)
    trail = [configured] + [e["knobs"] for e in run.changes()]
    assert len(trail) > 10
    assert [e["level"] for e in run.changes()] == sorted((e["level"] for e in run.changes()), reverse=True)
    for knob in METHODS[name].knobs:
        values = [t[knob.field] for t in trail]
        cheaper = values if knob.cheaper == "higher" else [-v for v in values]
        assert cheaper == sorted(cheaper), knob.field  # never back towards the configured value
        assert values[-1] == pytest.approx(FLOORS[name][knob.field])
    params = msgspec.structs.asdict(run.method.params)
    assert {k: params[k] for k in FLOORS[name]} == pytest.approx(FLOORS[name])
    if name == "rrm":
        assert run.method.params.cycle == 20
    # the integer knobs stay integers all the way down
    ints = [k for k in run.ctl.knobs if field_range(type(run.ctl.base), k)[2]]
    assert all(isinstance(t[k], int) for t in trail[1:] for k in ints)


def test_an_impossible_load_reaches_the_floor_and_then_nothing_changes(tracer):
    run = Run(tracer, "rrm")
    assert run.feed(5, 20.0, missed=True) == [None] * 5
    assert run.feed(1, 20.0, missed=True) == [{"fovea_deg": 5.0, "group_w": 5}]  # one drop to the bottom
    assert run.ctl.at_floor and run.ctl.level == 0.0
    assert run.changes()[-1]["reason"].endswith("(floor)")
    params, entries, calls = run.method.params, len(run.ctl.trajectory), len(run.calls)
    assert run.feed(200, 20.0, missed=True) == [None] * 200
    assert run.method.params is params and len(run.ctl.trajectory) == entries and len(run.calls) == calls
    assert run.ctl.at_floor and run.ctl.knobs == ("fovea_deg", "group_w")
    assert (params.fovea_deg, params.group_w, params.group_h) == (5.0, 5, 4)


def test_the_trajectory_keeps_the_start_and_the_newest_changes_and_counts_them_all(tracer):
    run = Run(tracer, "rrm", **EXACT)
    while run.ctl.changes <= LOGGED + 20 and run.frame < 50_000:
        run.feed(12, 1.25)  # drops
        run.feed(35, 0.25)  # a rise
    kept = run.ctl.trajectory
    assert len(kept) == LOGGED + 1 and kept[0]["reason"] == "start" and run.ctl.changes > LOGGED + 20
    frames = [e["frame"] for e in kept[1:]]
    assert frames == sorted(frames) and frames[-1] >= run.frame - 35  # the newest, in order


def test_the_drop_aims_at_the_middle_of_the_band_and_is_at_least_min_step(tracer):
    run = Run(tracer, "weier18", **EXACT)  # aim 0.75
    run.feed(6, 1.75)
    assert run.ctl.level == 0.5  # 0.5 x (1.75 - 0.75)
    run = Run(tracer, "weier18", **{**EXACT, "gain": 0.01, "min_step": 0.125})
    run.feed(6, 1.25)
    assert run.ctl.level == 0.875  # 0.01 x 0.5 is less than min_step


def test_it_recovers_by_up_step_after_raise_after_calm_frames_back_to_the_configured_params(tracer):
    run = Run(tracer, "weier16", **EXACT)
    run.feed(6, 1.25)
    assert run.ctl.level == 0.75 and run.method.params is not run.ctl.base
    drop_frame = run.frame - 1
    while run.ctl.level < 1.0 and run.frame < 1000:
        run.feed(1, 0.25)
    rises = run.changes()[1:]
    assert [e["frame"] for e in rises] == [drop_frame + 30 * (k + 1) for k in range(len(rises))]
    assert len(rises) in (5, 6)  # 0.75 + 5 x 0.05, give or take rounding, clamped at 1
    for before, entry in zip([0.75] + [e["level"] for e in rises], rises, strict=False):
        assert entry["level"] - before == pytest.approx(0.05, abs=1e-3) or entry["level"] == 1.0
        assert entry["reason"] == "under target: render 0.25 x target"
    # level 1 without widening: exactly the configured Params object, with its frc preset and no r0/r1/p_min
    assert run.calls[-1] is run.ctl.base and run.method.params is run.ctl.base
    assert run.method.params.r0 is None and run.method.params.frc == "medium"
    assert run.feed(100, 0.25) == [None] * 100  # level 1 cannot rise further


@pytest.mark.parametrize("r", [0.55, 0.75, 0.95, 1.0])
def test_between_raise_below_and_one_the_level_holds(tracer, r):
    run = Run(tracer, "kim21", **EXACT)  # raise_below 0.5
    run.feed(6, 1.25)
    entries, params = len(run.ctl.trajectory), run.method.params
    assert run.feed(300, r) == [None] * 300
    assert run.ctl.level == 0.75 and len(run.ctl.trajectory) == entries and run.method.params is params


def test_a_miss_in_the_calm_window_postpones_the_rise(tracer):
    run = Run(tracer, "weier16", target_miss_rate=0.5, **EXACT)  # one miss is not enough to drop
    run.feed(6, 1.25)
    run.feed(15, 0.25)  # frames 6 to 20
    run.feed(1, 0.25, missed=True)  # frame 21
    run.feed(60, 0.25)
    assert [e["frame"] for e in run.changes()] == [5, 51, 81]  # not 35: frames 22 to 51 are the first clean 30


@pytest.mark.parametrize(("r", "drop"), [(0.5, 0.1), (1.0, 0.1), (1.5, 0.6)])
def test_a_miss_over_the_allowed_rate_drops_at_least_miss_step(tracer, r, drop):
    run = Run(tracer, "rrm")
    run.feed(5, r)
    assert run.ctl.level == 1.0
    assert run.feed(1, r, missed=True)[0] is not None
    assert run.ctl.level == pytest.approx(1.0 - drop)  # max(miss_step, gain x (r - 0.9))
    assert run.changes()[-1]["reason"] == "miss: 1 of the last 6 frames missed"
    if r <= 1.0:  # the same frames without the miss hold the level
        quiet = Run(tracer, "rrm")
        assert quiet.feed(6, r) == [None] * 6 and quiet.ctl.level == 1.0


def test_misses_under_the_allowed_rate_do_not_drop_and_earlier_misses_count(tracer):
    run = Run(tracer, "rrm", target_miss_rate=0.2)
    run.feed(6, 0.5)
    run.feed(1, 0.5, missed=True)  # 1 of 7 is not over 0.2
    assert run.ctl.level == 1.0 and run.calls == []
    run = Run(tracer, "rrm", target_miss_rate=0.2)
    run.feed(1, 0.5)
    run.feed(2, 0.5, missed=True)  # while settling: no decision, but they count towards the rate
    run.feed(3, 0.5)
    assert run.ctl.level == 1.0
    run.feed(1, 0.5, missed=True)  # 3 of 7
    assert run.ctl.level == pytest.approx(0.9)
    assert run.changes()[-1]["reason"] == "miss: 3 of the last 7 frames missed"


@pytest.mark.parametrize("spec", ["full", "regular?spp=4"])
def test_a_method_without_knobs_is_left_alone_and_says_so(tracer, spec):
    run = Run(tracer, spec, accuracy_deg=2.0, widen_latency_ms=50.0)
    name = spec.partition("?")[0]
    base = run.method.params
    assert run.ctl.knobs == () and run.ctl.at_floor and run.ctl.level == 1.0
    assert run.ctl.trajectory == [
        {
            "frame": None,
            "level": 1.0,
            "knobs": {},
            "widen_deg": 0.0,
            "reason": f"{name} has no cost knobs: nothing to tune",
        }
    ]
    assert run.feed(100, 5.0, missed=True, speed=300.0) == [None] * 100
    assert run.method.params is base and run.calls == [] and len(run.ctl.trajectory) == 1
    assert run.ctl.widen_deg == 0.0 and run.ctl.widenings == 0


class ToyParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    cost: Annotated[int, msgspec.Meta(ge=1, le=16)] = 8
    radius: Annotated[float, msgspec.Meta(ge=0.0, le=90.0)] = 20.0
    gain: float = 1.0  # not a knob: never moved


class Toy(Configurable):
    """A method from outside the package: one module and its registry line, no word in the controller."""

    name = "toy"
    Params = ToyParams
    stages = (Stage("paint"),)
    knobs = (Knob("cost", 2), Knob("radius", 5.0, foveal=True))

    def __init__(self, tracer: Whitted, params: ToyParams):
        self.tracer = tracer
        self._configure(params)

    def _configure(self, params: ToyParams) -> None:
        self.params = params

    def render(self, request, stats, out=None):
        image = np.empty((request.camera.height, request.camera.width, 3), np.float32) if out is None else out
        image[:] = self.params.cost
        return image


def test_a_registered_method_is_tuned_by_the_knobs_it_declares(tracer, monkeypatch):
    monkeypatch.setitem(METHODS, "toy", Toy)
    run = Run(tracer, "toy?cost=12&radius=30", widen_latency_ms=50.0, **EXACT)
    assert run.ctl.knobs == ("cost", "radius") and run.ctl.trajectory[0]["knobs"] == {"cost": 12, "radius": 30.0}
    run.feed(6, 1.25)
    assert run.ctl.level == 0.75 and (run.method.params.cost, run.method.params.radius) == (10, 23.75)
    run.until_floor()
    assert run.method.params == ToyParams(cost=2, radius=5.0)  # the declared floors; gain untouched
    run.feed(1, 0.1, speed=100.0)  # a saccade widens the foveal knob only
    assert run.method.params.cost == 2 and run.method.params.radius > 5.0


def test_a_budget_that_is_not_positive_is_refused(tracer):
    ctl = Run(tracer, "weier16").ctl
    for budget in (0, -1):
        with pytest.raises(ValueError, match="budget_ns"):
            ctl.update(0, 1_000_000, budget, False)


# foveal widening


@pytest.mark.parametrize(
    ("speed", "accuracy", "step", "widen"),
    [
        (100.0, 0.0, 0.5, 2.0),  # 100 deg/s x 20 ms: exactly a multiple, not rounded up further
        (100.0, 0.7, 0.5, 3.0),  # 2.7 rounds up
        (102.5, 0.0, 0.5, 2.5),  # 2.05 rounds up
        (100.0, 0.7, 0.0, 2.7),  # step 0: exact
        (100.0, 0.7, 2.0, 4.0),
    ],
)
def test_gaze_speed_and_accuracy_widen_the_fovea_at_once_rounded_up(tracer, speed, accuracy, step, widen):
    run = Run(tracer, "weier16", widen_latency_ms=20.0, accuracy_deg=accuracy, widen_step_deg=step)
    out = run.feed(1, 0.9, speed=speed)[0]
    assert out == pytest.approx({"r0": 10.0 + widen, "r1": 20.0 + widen, "p_min": 0.05})
    assert run.ctl.widen_deg == pytest.approx(widen)
    assert (run.method.params.r0, run.method.params.r1) == pytest.approx((10.0 + widen, 20.0 + widen))
    assert run.ctl.level == 1.0 and len(run.ctl.trajectory) == 1 and run.ctl.widenings == 1
    assert run.feed(10, 0.9, speed=speed) == [None] * 10 and len(run.calls) == 1


@pytest.mark.parametrize("name", TUNABLE)
def test_widening_moves_the_foveal_knobs_only(tracer, name):
    run = Run(tracer, name, accuracy_deg=2.0)
    configured = run.method.knob_values(run.ctl.base)
    out = run.feed(1, 0.9)[0]
    assert out == pytest.approx({k: configured[k] + (2.0 if k in FOVEAL[name] else 0.0) for k in run.ctl.knobs})
    params = msgspec.structs.asdict(run.method.params)
    assert {k: params[k] for k in FOVEAL[name]} == pytest.approx({k: configured[k] + 2.0 for k in FOVEAL[name]})


def test_the_widening_shrinks_only_after_settle_frames_without_growth(tracer):
    run = Run(tracer, "weier16", widen_latency_ms=20.0, accuracy_deg=0.7)
    assert run.feed(1, 0.9, speed=100.0)[0]["r0"] == 13.0  # frame 0: 2.7 -> 3
    assert run.feed(5, 0.9, speed=0.0) == [None] * 5  # frames 1-5 keep it
    assert run.method.params.r0 == 13.0
    assert run.feed(1, 0.9, speed=0.0)[0] == pytest.approx({"r0": 11.0, "r1": 21.0, "p_min": 0.05})  # frame 6
    assert run.ctl.widen_deg == 1.0 and run.feed(20, 0.9, speed=0.0) == [None] * 20  # accuracy stays covered
    assert run.ctl.widenings == 2 and len(run.ctl.trajectory) == 1  # widening is not a level change

    run = Run(tracer, "weier16", widen_latency_ms=20.0, accuracy_deg=0.7)
    out = run.feed(3, 0.9, speed=100.0) + run.feed(1, 0.9, speed=150.0) + run.feed(12, 0.9, speed=0.0)
    changed = {f: v["r0"] for f, v in enumerate(out) if v is not None}
    assert changed == {0: 13.0, 3: 14.0, 9: 11.0}  # growth at frame 3 restarts the wait


@pytest.mark.parametrize("speed", [None, math.nan, math.inf, -math.inf, -50.0])
def test_an_unknown_or_negative_speed_widens_for_accuracy_alone(tracer, speed):
    run = Run(tracer, "rrm", widen_latency_ms=50.0, accuracy_deg=0.7)
    assert run.feed(1, 0.9, speed=speed) == [{"fovea_deg": 11.0, "group_w": 3}]
    run = Run(tracer, "rrm", widen_latency_ms=50.0)
    assert run.feed(10, 0.9, speed=speed) == [None] * 10
    assert run.method.params is run.ctl.base and run.ctl.widen_deg == 0.0


def test_the_widening_adds_to_the_level_value_and_is_clamped_to_the_valid_range(tracer):
    run = Run(tracer, "weier16", accuracy_deg=1.0, **EXACT)
    run.feed(6, 1.25)
    assert (run.method.params.r0, run.method.params.r1) == pytest.approx((9.75, 18.5))  # level 0.75 + 1 deg
    assert run.method.params.p_min == pytest.approx(0.04)

    run = Run(tracer, "weier16?r1=178", accuracy_deg=5.0)
    assert run.feed(1, 0.9)[0] == pytest.approx({"r0": 15.0, "r1": 180.0, "p_min": 0.05})
    assert run.method.params.r1 == 180.0

    run = Run(tracer, "weier16?frc=full", accuracy_deg=5.0)  # infinite radii: 180, already the largest
    assert run.ctl.trajectory[0]["knobs"] == {"r0": 180.0, "r1": 180.0, "p_min": 1.0}
    assert run.feed(10, 0.9) == [None] * 10
    assert run.method.params is run.ctl.base and run.calls == [] and run.ctl.widen_deg == 5.0


def test_back_at_level_one_without_widening_the_configured_params_object_returns(tracer):
    run = Run(tracer, "kim21", accuracy_deg=0.0, widen_latency_ms=10.0)
    run.feed(1, 0.9, speed=200.0)  # 2 deg
    assert run.method.params is not run.ctl.base and run.method.params.e_f == pytest.approx(5.3)
    run.feed(6, 0.9, speed=0.0)
    assert run.calls[-1] is run.ctl.base and run.method.params is run.ctl.base


# floors and parameters


def test_a_knob_configured_below_its_floor_stays_put(tracer):
    run = Run(tracer, "weier16?r0=2&p_min=0.001")
    run.until_floor()
    assert all(e["knobs"]["r0"] == 2.0 and e["knobs"]["p_min"] == 0.001 for e in run.changes())
    p = run.method.params
    assert (p.r0, p.r1, p.p_min) == (2.0, 10.0, 0.001)


@pytest.mark.parametrize(("group_h", "floor"), [(4, 5), (5, 4), (2, 10), (7, 3), (30, 3)])
def test_rrm_groups_grow_until_n_reaches_20_but_never_shrink(tracer, group_h, floor):
    run = Run(tracer, f"rrm?group_h={group_h}")
    run.until_floor()
    assert run.method.params.group_w == floor and run.method.params.group_h == group_h
    if floor > 3:  # grown: the largest N up to 20
        assert run.method.params.cycle <= 20 < (floor + 1) * group_h


def test_spans_resolve_the_weier16_preset_and_the_fields_ranges():
    assert Weier16.knob_values(Weier16Params()) == {
        **msgspec.structs.asdict(Weier16Params()),
        "r0": 10.0,
        "r1": 20.0,
        "p_min": 0.05,
    }
    assert [Weier16.knob_values(Weier16Params(frc=f))["r0"] for f in ("small", "medium", "large", "full")] == [
        5.0,
        10.0,
        15.0,
        math.inf,
    ]
    v = Weier16.knob_values(Weier16Params(frc="small", r1=12.0))
    assert (v["r0"], v["r1"], v["p_min"]) == (5.0, 12.0, 0.01)
    assert Rrm.knob_values(RrmParams()) == msgspec.structs.asdict(RrmParams())

    assert field_range(Weier16Params, "r0") == (0.0, 180.0, False)  # optional field: its number type
    assert field_range(RrmParams, "group_w") == (1, 64, True)
    assert field_range(Kim21Params, "n_f") == (1, 16, True)
    assert field_range(Weier18Params, "pupil_mm") == (0.0, 20.0, False)

    large = {s.field: s for s in spans(Weier16, Weier16Params(frc="large"))}
    assert {k: (s.top, s.bottom) for k, s in large.items()} == {"r0": (15, 5), "r1": (30, 10), "p_min": (0.1, 0.01)}
    full = {s.field: s for s in spans(Weier16, Weier16Params(frc="full"))}
    assert {k: (s.top, s.bottom) for k, s in full.items()} == {"r0": (180, 5), "r1": (180, 10), "p_min": (1.0, 0.01)}
    rrm = {s.field: s for s in spans(Rrm, RrmParams(group_h=5))}
    assert (rrm["group_w"].top, rrm["group_w"].bottom, rrm["group_w"].integer) == (3, 4, True)
    kim = {s.field: s for s in spans(Kim21, Kim21Params())}
    assert kim["e_f"].top == kim["e_f"].bottom == 3.3 and kim["e_f"].foveal and not kim["n_f"].foveal


def test_a_frc_preset_level_keeps_the_preset_and_sets_the_radii(tracer):
    run = Run(tracer, "weier16?frc=large", **EXACT)
    run.feed(6, 1.25)
    p = run.method.params
    assert p.frc == "large" and (p.r0, p.r1, p.p_min) == pytest.approx((12.5, 25.0, 0.0775))
    assert run.method.foveal == pytest.approx((12.5, 25.0, 0.0775))


@pytest.mark.parametrize("name", list(METHODS))
def test_set_params_refuses_another_methods_params_unchanged(tracer, name):
    method = make_method(name, tracer)
    before = method.params
    wrong = RrmParams() if name != "rrm" else NoParams()
    with pytest.raises(TypeError, match=type(wrong).__name__):
        method.set_params(wrong)
    assert method.params is before


def test_set_params_refuses_values_only_the_method_can_check_unchanged(tracer):
    weier16 = make_method("weier16", tracer)
    before, foveal = weier16.params, weier16.foveal
    with pytest.raises(ConfigError, match="r0"):
        weier16.set_params(Weier16Params(r0=30.0))  # above medium's r1 = 20
    assert weier16.params is before and weier16.foveal == foveal

    kim21 = make_method("kim21", tracer)
    before = kim21.params
    with pytest.raises(ConfigError, match="tau"):
        kim21.set_params(Kim21Params(tau_f_slope=0.0))
    assert kim21.params is before


# refusals

EDGE_BANDS = "kim21?e_f=150&e_p=155&e_m=160&e_np=175&e_max=180"  # widened, e_np clamps at 180 under tau's shape


def test_a_refused_change_is_recorded_once_and_not_retried(tracer):
    run = Run(tracer, EDGE_BANDS, accuracy_deg=20.0)
    assert run.feed(1, 0.9) == [None]
    assert len(run.calls) == 1 and run.method.params is run.ctl.base
    assert run.ctl.trajectory[-1]["reason"].startswith("refused {") and "tau_fov" in run.ctl.trajectory[-1]["reason"]
    assert run.ctl.trajectory[-1]["level"] == 1.0 and run.ctl.trajectory[-1]["frame"] == 0
    assert run.feed(4, 0.9) == [None] * 4
    assert len(run.calls) == 1 and len(run.ctl.trajectory) == 2


def test_a_level_is_not_taken_while_its_knobs_are_refused(tracer):
    run = Run(tracer, EDGE_BANDS, accuracy_deg=20.0)
    run.feed(40, 1.5)
    for entry in run.changes():
        assert entry["knobs"]["n_f"] < 9, entry  # a lower level shows in the knobs it applied
    assert not run.ctl.at_floor or run.method.params.n_f == 1
