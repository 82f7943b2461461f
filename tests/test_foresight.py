"""Foresight: the probe of the fovea on the real tracer, the cost model, and the controller picking each frame's level
from its predicted render time before the frame is rendered (hmdrt.compositor.foresight, controller "Foresight")."""

import math

import numpy as np
import pytest

from hmdrt.compositor.controller import BudgetController, ControllerConfig
from hmdrt.compositor.foresight import GRID, STALE, CostModel, Foresight, FovealProbe
from hmdrt.foveation import make_method
from hmdrt.foveation.stages.sampling import pixels_per_degree
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

BUDGET_NS = 30_000_000


@pytest.fixture(scope="module")
def tracer(whitted_scene):
    with Whitted(whitted_scene) as t:
        yield t


@pytest.fixture(scope="module")
def cameras(whitted_scene):
    profile = get_profile("sim-cpu-640")
    return {eye: EyeCamera.for_eye(profile, whitted_scene.start, eye) for eye in ("left", "right")}


def gaze_at(camera: EyeCamera, x: float, y: float) -> np.ndarray:
    """The head-frame gaze through pixel (x, y)."""
    d = camera.directions(np.array([[x, y]], np.float32))[0].astype(np.float64)
    return camera.rotation.T @ d


def test_the_probe_counts_the_rays_of_its_grid_and_the_pixels_of_every_eyes_square(tracer, cameras):
    probe = FovealProbe(tracer, stride=8)
    left = cameras["left"]
    gaze = gaze_at(left, 320, 360)
    fore = probe.read(cameras, {"left": gaze, "right": gaze}, 5.0)
    ppd_x, ppd_y = pixels_per_degree(left)
    half_x, half_y = 5.0 * ppd_x, 5.0 * ppd_y
    side = (math.ceil(320 + half_x) - math.floor(320 - half_x), math.ceil(360 + half_y) - math.floor(360 - half_y))
    assert fore.pixels == 2 * side[0] * side[1] and fore.radius_deg == 5.0
    # the same grid traced apart: as many rays per sample
    xs, ys = np.arange(math.floor(320 - half_x), 320 + half_x, 8), np.arange(math.floor(360 - half_y), 360 + half_y, 8)
    xy = np.stack(np.meshgrid(xs + 0.5, ys + 0.5), -1).reshape(-1, 2).astype(np.float32)
    stats = FrameStats()
    tracer.trace_samples(left, xy, np.arange(len(xy), dtype=np.int64), stats)
    assert fore.rays_per_pixel == pytest.approx(sum(stats.rays.values()) / len(xy))


def test_the_probe_reads_more_rays_where_the_fovea_lands_on_glass(tracer, cameras):
    """whitted's glass and mirror spheres spawn reflected and refracted rays three deep: a fovea on them costs
    several times what one on the floor does, which is what a landing there does to a frame."""
    probe, left = FovealProbe(tracer), cameras["left"]
    readings = []
    for x in range(40, 640, 80):
        for y in range(40, 720, 80):
            g = gaze_at(left, x, y)
            readings.append(probe.read(cameras, {"left": g, "right": g}, 3.0).rays_per_pixel)
    assert min(readings) >= 1.0 and max(readings) > 2.5 * min(readings)


def test_a_square_off_the_image_reads_nothing(tracer, cameras):
    behind = np.array([0.0, 0.0, 1.0])
    assert FovealProbe(tracer).read(cameras, {"left": behind, "right": behind}, 10.0) == Foresight(0.0, 0, 10.0)
    with pytest.raises(ValueError, match="stride"):
        FovealProbe(tracer, stride=0)


def test_the_model_predicts_the_rest_of_a_level_plus_the_fovea_at_its_radius():
    model = CostModel()
    fore = Foresight(2.0, 1000, 10.0)  # 2000 foveal rays at radius 10
    assert math.isnan(model.predict(1.0, fore, 10.0))
    model.learn(1.0, 10.0, 10_000_000, 10_000, fore, False)  # 1000 ns a ray, 8000 rays of rest
    assert model.predict(1.0, fore, 10.0) == pytest.approx(10_000_000)
    assert model.predict(1.0, Foresight(6.0, 1000, 10.0), 10.0) == pytest.approx(14_000_000)  # the fovea on glass
    assert model.predict(1.0, fore, 5.0) == pytest.approx(8_500_000)  # a quarter of the pixels
    assert model.predict(0.0, fore, 10.0) == pytest.approx(10_000_000)  # the only level known stands for all
    model.learn(0.0, 5.0, 4_000_000, 4000, Foresight(2.0, 1000, 10.0), False)  # 3500 rays of rest at level 0
    assert model.predict(0.5, fore, 5.0) == pytest.approx(1000 * ((3500 + 8000) / 2 + 500))


def test_learning_smooths_the_rest_and_the_time_per_ray():
    model, fore = CostModel(), Foresight(1.0, 1000, 10.0)
    model.learn(1.0, 10.0, 10_000_000, 10_000, fore, False)
    model.learn(1.0, 10.0, 20_000_000, 10_000, fore, False)  # a slow frame: the means move 30% of the way
    ns_per_ray = 1000 + 0.3 * (2000 - 1000)
    rest = 9_000_000 + 0.3 * (20_000_000 - ns_per_ray * 1000 - 9_000_000)
    assert model.predict(1.0, fore, 10.0) == pytest.approx(rest + ns_per_ray * 1000)
    model.learn(1.0, 10.0, 0, 0, fore, False)  # nothing learnt from an empty frame
    assert model.predict(1.0, fore, 10.0) == pytest.approx(rest + ns_per_ray * 1000)
    assert GRID == 20


def test_the_model_tells_a_foveal_rays_cost_from_the_mean_rays():
    """Glass's reflected and refracted rays cost more than the floor's primary ones: at a level, render time climbs
    with the fovea's rays faster than the mean ray's cost says, and the model learns that slope."""
    model, rng = CostModel(), np.random.default_rng(1)
    for _ in range(400):
        rays_per_pixel = rng.uniform(1.0, 5.0)
        fovea = 10_000 * rays_per_pixel
        model.learn(
            1.0,
            10.0,
            round(5_000_000 + 300 * fovea),
            round(50_000 + fovea),
            fore := Foresight(rays_per_pixel, 10_000, 10.0),
            False,
        )
    assert model.ns_per_foveal_ray == pytest.approx(300, rel=0.05)
    landing = Foresight(5.0, 10_000, 10.0)
    assert model.predict(1.0, landing, 10.0) == pytest.approx(5_000_000 + 300 * 50_000, rel=0.02)
    assert fore.radius_deg == 10.0


def test_a_change_of_level_costs_what_it_has_cost_beyond_the_prediction():
    model, fore = CostModel(), Foresight(1.0, 1000, 10.0)
    model.learn(1.0, 10.0, 10_000_000, 10_000, fore, False)  # nothing to fall short of yet
    model.learn(1.0, 10.0, 10_000_000, 10_000, fore, False)  # as predicted
    assert model.change_ns == 0.0
    model.learn(1.0, 10.0, 15_000_000, 10_000, fore, True)  # 5 ms over its prediction after a change
    assert model.change_ns == pytest.approx(5_000_000)


def test_a_level_left_long_ago_gives_way_to_the_fresh_ones():
    model, fore = CostModel(), Foresight(1.0, 1000, 10.0)
    model.learn(1.0, 10.0, 90_000_000, 10_000, fore, False)  # a warm-up frame: 9000 ns a ray
    for _ in range(STALE - 1):
        model.learn(0.0, 10.0, 10_000_000, 10_000, fore, False)
    stale = model.predict(1.0, fore, 10.0)
    model.learn(0.0, 10.0, 10_000_000, 10_000, fore, False)
    assert stale > 20_000_000 and model.predict(1.0, fore, 10.0) == pytest.approx(model.predict(0.0, fore, 10.0))


class Frames:
    """A foresighted controller over real rrm, fed frames whose cost is rays x 1000 ns: its fovea's pixels at the
    level's radius times the rays per pixel of where the gaze is, plus a rest that falls with the level."""

    def __init__(self, tracer: Whitted, **settings):
        self.method = make_method("rrm", tracer)
        self.ctl = BudgetController(self.method, ControllerConfig(foresight=True, headroom=1.0, **settings))
        self.frame, self.levels = 0, []

    def rays(self, rays_per_pixel: float) -> tuple[Foresight, int]:
        radius = self.method.params.fovea_deg
        fore = Foresight(rays_per_pixel, round(100 * radius**2), radius)
        return fore, round(5000 + 10_000 * self.ctl.level + fore.rays(radius))

    def feed(self, rays_per_pixel: float, missed: bool = False, scale: float = 1.0) -> float:
        """One frame: the probe reads the fovea, the controller picks the level, the frame is rendered (in `scale` x
        its time) and learnt of; the level it was rendered at."""
        radius = self.method.params.fovea_deg
        self.ctl.anticipate(self.frame, Foresight(rays_per_pixel, round(100 * radius**2), radius))
        fore, rays = self.rays(rays_per_pixel)
        self.levels.append(self.ctl.level)
        self.ctl.update(self.frame, round(rays * 1000 * scale), BUDGET_NS, missed, rays=rays)
        self.frame += 1
        return self.levels[-1]


def test_a_landing_on_costly_content_lowers_the_level_before_its_frame_and_leaving_it_restores_it(tracer):
    f = Frames(tracer)
    assert f.ctl.foresees and f.ctl.fovea_deg == 10.0
    for _ in range(5):  # level 1 takes 25 ms, over 0.7 of 30: it settles at the highest level predicted to fit
        f.feed(1.0)
    calm = f.levels[-1]
    predicted = f.ctl.model.predict(calm, Foresight(1.0, 10_000, 10.0), f.method.params.fovea_deg)
    assert predicted <= f.ctl.fit * BUDGET_NS
    landing = f.feed(4.0)  # the gaze lands on glass: four times the fovea's rays
    assert landing < calm and f.method.params.fovea_deg < 10.0
    fore, rays = f.rays(4.0)
    assert rays * 1000 <= f.ctl.fit * BUDGET_NS * 1.05  # the landing frame itself fits
    assert f.ctl.trajectory[-1]["reason"].startswith("foresight:")
    for _ in range(3):
        f.feed(4.0)
    assert f.feed(1.0) == calm  # back on the floor: the level it held there, at once


def test_a_slow_start_does_not_hold_the_level_down(tracer):
    """The warm-up's first frames take several times their due (compiles, a watcher connecting): the levels left then
    are predicted afresh once STALE frames have passed, and the level climbs back."""
    f = Frames(tracer)
    for _ in range(20):
        f.feed(1.0, scale=4.0)
    assert f.levels[-1] == 0.0
    for _ in range(STALE + 30):
        f.feed(1.0)
    assert f.levels[-1] >= 0.6


def test_misses_over_the_target_tighten_the_fit_and_calm_frames_ease_it_back(tracer):
    settings = {"target_miss_rate": 0.01, "miss_window": 60, "raise_after": 30}
    tight, loose = Frames(tracer, **settings), Frames(tracer, **settings)
    for f in (tight, loose):
        f.feed(1.0)
        f.feed(1.0, missed=f is tight)
    c = loose.ctl.config
    assert tight.ctl.fit == pytest.approx(c.foresight_fit - c.miss_step) and loose.ctl.fit == c.foresight_fit
    for _ in range(5):
        tight.feed(1.0), loose.feed(1.0)
    assert tight.levels[-1] < loose.levels[-1]  # the same frames, rendered within a tighter fit
    for _ in range(31):
        tight.feed(1.0)
    assert tight.ctl.fit == pytest.approx(c.foresight_fit - c.miss_step + c.up_step)


def test_without_foresight_or_a_foveal_knob_anticipate_leaves_the_level(tracer):
    ctl = BudgetController(make_method("rrm", tracer), ControllerConfig())
    assert not ctl.foresees and ctl.anticipate(0, Foresight(9.0, 100, 10.0)) is None and ctl.level == 1.0
    full = BudgetController(make_method("full", tracer), ControllerConfig(foresight=True))
    assert not full.foresees and full.fovea_deg is None
