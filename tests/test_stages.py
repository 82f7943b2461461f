"""The shared foveation stages against the papers' formulas and hand-computed values."""

import math

import numpy as np
import pytest

from hmdrt.errors import ConfigError
from hmdrt.foveation.kim21 import Kim21Params, alpha_of_eccentricity, bezier_controls, tau_fov_array
from hmdrt.foveation.rrm import RrmParams
from hmdrt.foveation.stages.dof import (
    DOF_PRESETS,
    REFERENCE_PPD,
    circle_of_confusion,
    coc_map,
    focal_lengths,
)
from hmdrt.foveation.stages.gaze import FixationFilter, vergence_depth
from hmdrt.foveation.stages.refresh import RefreshSchedule, refresh_phase, visit_order
from hmdrt.foveation.stages.sampling import (
    FRC_PRESETS,
    bernoulli_mask,
    expected_fraction,
    foveal_config,
    pixels_per_degree,
    sampling_tables,
    table_mask,
    transition_points,
    transition_radius,
    transition_radius_linear,
)
from hmdrt.foveation.stages.temporal import History, exponential_smoothing, k_of_age, running_estimate
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.optics.camera import pixel_centres
from hmdrt.optics.projection import FAR
from hmdrt.spatial import Pose, gaze_direction


def camera(profile="rift_s", pose=None, width=None, height=None):
    p = get_profile(profile)
    if width:
        p = p.with_resolution(width, height)
    return EyeCamera.for_eye(p, pose or Pose.looking((0.0, 1.6, 0.0)))


# -- weier2016 section 3.4: running estimate and k(dt) --


def test_running_estimate_matches_hand_computed_values():
    # rho_{t-1} = 1: alpha' = 1/2; k = 0.1 < 1/2, so alpha = 1/2; rho = (1/4 + 1/4 / 1)^-1 = 2
    assert running_estimate(1.0, 0.1) == pytest.approx((0.5, 2.0))
    # rho_{t-1} = 3: alpha' = 1/4; rho = (1/16 + (9/16) / 3)^-1 = 1 / (1/16 + 3/16) = 4
    assert running_estimate(3.0, 0.1) == pytest.approx((0.25, 4.0))
    # k above alpha' bounds the new sample's weight from below: alpha = 0.6, rho = 1/(0.36 + 0.16/9)
    alpha, rho = running_estimate(9.0, 0.6)
    assert alpha == pytest.approx(0.6) and rho == pytest.approx(1.0 / (0.36 + 0.16 / 9.0))


def test_running_estimate_counts_samples_until_k_bounds_it():
    rho = 1.0
    for n in range(2, 8):
        alpha, rho = running_estimate(rho, 1e-6)
        assert alpha == pytest.approx(1.0 / n) and rho == pytest.approx(n)  # an exact average of n samples


def test_k_of_age_matches_the_formula():
    k_min, k_max, t_max = 0.05, 0.8, 11.0
    x0, x1 = math.log(k_min), math.log(k_max)
    for dt in (1, 2, 6, 11, 30):
        expected = min(math.exp(x0 + (dt - 1) / (t_max - 1) * (x1 - x0)), k_max)
        assert k_of_age(float(dt), k_min, k_max, t_max) == pytest.approx(expected)
    assert k_of_age(1.0, k_min, k_max, t_max) == pytest.approx(k_min)
    assert k_of_age(11.0, k_min, k_max, t_max) == pytest.approx(k_max)
    assert k_of_age(6.0, k_min, k_max, t_max) == pytest.approx(math.sqrt(k_min * k_max))  # geometric midpoint
    assert k_of_age(5.0, k_min, k_max, 1.0) == k_max  # t_max = 1 would divide by zero


# -- weier2016 section 3.1 and weier2018 section 3.1: sampling --


def test_frc_presets_are_the_papers():
    assert FRC_PRESETS["small"] == (5.0, 10.0, 0.01)
    assert FRC_PRESETS["medium"] == (10.0, 20.0, 0.05)
    assert FRC_PRESETS["large"] == (15.0, 30.0, 0.1)
    with pytest.raises(ConfigError, match="must not exceed"):
        foveal_config("medium", 30.0, 20.0, None)


@pytest.mark.parametrize("frc", ["small", "medium", "large"])
def test_sample_fraction_matches_the_foveal_function(frc):
    cam = camera()
    ecc = cam.eccentricity(gaze_direction(8.0, -4.0))
    cfg = foveal_config(frc, None, None, None)
    expected = expected_fraction(ecc, cfg)
    fractions = [bernoulli_mask(ecc, cfg, seed=3, frame=f).mean() for f in range(3)]
    for f in fractions:
        assert abs(f - expected) <= 0.02 * expected
    masks = [bernoulli_mask(ecc, cfg, 3, f) for f in range(2)]
    assert np.all(masks[0][ecc < cfg.r0]) and not np.array_equal(masks[0], masks[1])  # fresh xi every frame


def test_equation_1_limits_and_distribution():
    u = np.linspace(0.0, 1.0, 11)
    np.testing.assert_allclose(transition_radius(u, 10, 20, 1.0), 10 + 10 * u)  # p_min = 1: uniform
    near_one = transition_radius(u, 10, 20, 1.0 - 1e-12)
    np.testing.assert_allclose(near_one, 10 + 10 * u, atol=1e-9)  # no 0/0 near the limit
    assert transition_radius(0.0, 10, 20, 0.05) == 10 and transition_radius(1.0, 10, 20, 0.05) == pytest.approx(20)
    # the inverse of the CDF of f(x) = 1 - x (1 - p): F(x) = (2x - (1 - p) x^2) / (1 + p)
    p = 0.2
    x = transition_radius(u, 0.0, 1.0, p)
    np.testing.assert_allclose((2 * x - (1 - p) * x * x) / (1 + p), u, atol=1e-12)


def test_linear_density_falls_linearly_per_unit_area():
    """density=linear: the points per unit area of each ring follow f(r) = 1 - (1 - p)(r - r0)/(r1 - r0), where
    equation (1) as printed gives f(r) / r; both end at r0 and r1."""
    r0, r1, p = 10.0, 20.0, 0.2
    u = (np.arange(200_000) + 0.5) / 200_000
    edges = np.linspace(r0, r1, 11)
    mid = 0.5 * (edges[:-1] + edges[1:])
    f = 1 - (1 - p) * (mid - r0) / (r1 - r0)
    for radius, expected in ((transition_radius_linear, f), (transition_radius, f / mid)):
        r = radius(u, r0, r1, p)
        assert r[0] == pytest.approx(r0, abs=1e-3) and r[-1] == pytest.approx(r1, abs=1e-3)
        assert np.all(np.diff(r) > 0)
        per_area = np.histogram(r, edges)[0] / (edges[1:] ** 2 - edges[:-1] ** 2)
        np.testing.assert_allclose(per_area / per_area[0], expected / expected[0], rtol=0.02)
    np.testing.assert_allclose(transition_radius_linear(u[::997], 0.0, 1.0, 1.0), np.sqrt(u[::997]), atol=1e-9)


def test_s_in_reproduces_the_density_of_equation_1():
    cam = camera()
    cfg = foveal_config("medium", None, None, 0.05)
    tables = sampling_tables(cam, cfg)
    ppd_x, ppd_y = tables.ppd
    points = transition_points(cfg, tables.samples, tables.ppd)
    r = np.hypot(points[:, 0] / ppd_x, points[:, 1] / ppd_y)
    # the points' radii follow equation (1): F(x) = (2x - (1 - p) x^2) / (1 + p), x = (r - r0) / (r1 - r0)
    x = np.sort((r - cfg.r0) / (cfg.r1 - cfg.r0))
    cdf = (2 * x - (1 - cfg.p_min) * x * x) / (1 + cfg.p_min)
    assert np.max(np.abs(np.arange(1, len(x) + 1) / len(x) - cdf)) < 5.0 / len(x) ** 0.5  # KS, low discrepancy
    assert np.all((r >= cfg.r0) & (r < cfg.r1 + 1e-9))
    # S_in is every pixel inside r0 and the pixels the points land on; a point whose pixel an earlier one took
    # moves along its circle to a free one, so the band holds one marked pixel per point (but where the printed
    # density next to r0 exceeds one per pixel)
    ry, rx = tables.s_in.shape[0] // 2, tables.s_in.shape[1] // 2
    oy, ox = np.mgrid[-ry : ry + 1, -rx : rx + 1]
    r_pix = np.hypot(ox / ppd_x, oy / ppd_y)
    assert tables.s_in[r_pix < cfg.r0].all()
    hit = np.rint(points).astype(int)
    assert tables.s_in[hit[:, 1] + ry, hit[:, 0] + rx].all()
    assert 0.95 * len(points) <= tables.s_in[r_pix >= cfg.r0].sum() <= len(points)
    # M is the transition band's expected count under the linear falloff of weier2016
    band = (r_pix >= cfg.r0) & (r_pix < cfg.r1)
    falloff = 1 - (1 - cfg.p_min) * (r_pix[band] - cfg.r0) / (cfg.r1 - cfg.r0)
    assert tables.samples == round(falloff.sum())


def test_table_mask_uses_s_out_outside_r1_and_moves_s_in_with_the_gaze():
    cam = camera()
    cfg = foveal_config("medium", None, None, 0.2)
    tables = sampling_tables(cam, cfg, seed=5)
    for yaw in (0.0, 12.0):
        g = gaze_direction(yaw, 0.0)
        ecc = cam.eccentricity(g)
        mask = table_mask(cam, g, ecc, cfg, tables)
        outside = ecc >= cfg.r1
        np.testing.assert_array_equal(mask[outside], tables.s_out[outside])
        assert np.all(mask[ecc < cfg.r0])
        assert abs(mask[outside].mean() - 0.2) < 0.01


# -- kim2021 section 4.6.1: tau_fov --


def test_tau_fov_is_c1_at_e_f_and_monotone():
    for shape in ((1.0, 2.0, 0.5, 12.0), (9.0, 10.0, 1.5, 20.0)):  # Figure 7's two functions
        p = Kim21Params(tau_0=shape[0], tau_f=shape[1], tau_f_slope=shape[2], tau_np=shape[3])
        ctrl = bezier_controls(p)
        e = np.linspace(0.0, p.e_np, 3001)
        tau = tau_fov_array(e, ctrl)
        assert tau[0] == pytest.approx(shape[0]) and tau[-1] == pytest.approx(shape[3])
        assert tau_fov_array(np.array([p.e_f]), ctrl)[0] == pytest.approx(shape[1])
        assert np.all(np.diff(tau) >= -1e-12)  # monotone
        h = 1e-4
        left = (tau_fov_array(np.array([p.e_f]), ctrl)[0] - tau_fov_array(np.array([p.e_f - h]), ctrl)[0]) / h
        right = (tau_fov_array(np.array([p.e_f + h]), ctrl)[0] - tau_fov_array(np.array([p.e_f]), ctrl)[0]) / h
        assert left == pytest.approx(shape[2], rel=1e-2) and right == pytest.approx(shape[2], rel=1e-2)  # C1
        slope0 = (tau_fov_array(np.array([h]), ctrl)[0] - shape[0]) / h
        assert abs(slope0) < 1e-2  # flat at the fixation


def test_tau_fov_rejects_shapes_that_are_not_functions_and_takes_flat_ones():
    with pytest.raises(ConfigError, match="function of eccentricity"):
        bezier_controls(Kim21Params(tau_0=1.0, tau_f=10.0, tau_f_slope=0.5, tau_np=12.0))
    with pytest.raises(ConfigError, match="tau_f_slope must be positive"):
        bezier_controls(Kim21Params(tau_0=1.0, tau_f=2.0, tau_f_slope=0.0, tau_np=12.0))
    flat = bezier_controls(Kim21Params(tau_0=3.0, tau_f=3.0, tau_f_slope=0.0, tau_np=3.0))
    np.testing.assert_allclose(tau_fov_array(np.linspace(0, 30, 50), flat), 3.0)


def test_alpha_of_eccentricity_is_the_papers_piecewise_linear_function():
    p = Kim21Params()
    e = np.array([0.0, p.e_f, p.e_p, p.e_m, p.e_np, p.e_max, 60.0, (p.e_f + p.e_p) / 2])
    np.testing.assert_allclose(alpha_of_eccentricity(e, p), [0.9, 0.8, 0.7, 0.5, 0.2, 0.1, 0.1, 0.75], rtol=1e-6)


# -- kim2021 section 4.7: the smoothing history --


def test_history_keeps_the_newest_frames_and_restart_keeps_the_newest_readable():
    history = History(2)
    cam = camera(width=4, height=3)
    for k in range(4):
        slot = history.begin((3, 4))
        assert slot not in history.order((3, 4))  # the frame being rendered never overwrites one still in use
        history.depth[slot] = k
        history.color[slot] = k
        history.commit(cam)
    assert [history.depth[s, 0, 0] for s in history.order((3, 4))] == [3.0, 2.0]
    history.restart()
    assert len(history.order((3, 4))) == 0 and history.depth[history.newest((3, 4)), 0, 0] == 3.0
    assert history.newest((4, 4)) == -1 and len(history.order((4, 4))) == 0


def test_kim21_smoothing_reads_frames_of_the_same_camera_in_place():
    """The fast path (earlier frames seen by the current camera) equals back-projection into a camera 1 nm away."""
    cam = camera(width=24, height=16)
    moved = EyeCamera(**{**cam.__dict__, "position": cam.position + 1e-9})
    rng = np.random.default_rng(3)
    depth = rng.uniform(1.0, 3.0, (16, 24)).astype(np.float32)
    depth[:4] = np.inf  # sky: misses match misses
    alpha = rng.uniform(0.0, 1.0, (16, 24)).astype(np.float32)
    colors = rng.random((4, 16, 24, 3), dtype=np.float32)
    images = []
    for earlier in (cam, moved):
        history = History(4)
        for c in colors[:3]:
            history.push(earlier, depth, c)
        images.append(exponential_smoothing(cam, depth, colors[3], alpha, history, 4, 0.02))
    assert not np.allclose(images[0], colors[3], atol=1e-3)  # the earlier frames count
    np.testing.assert_allclose(images[0], images[1], atol=1e-5)


def _smoothed_by_hand(cam, depth, color, alpha, earlier, rel_depth):
    """kim2021 section 4.7's closed form pixel by pixel from the cameras' geometry: each pixel's surface point in
    the world, seen by each earlier camera (newest first), its depth read at the texel it lands in and its colour
    bilinearly with edge texels repeated."""
    h, w = depth.shape
    out = np.empty_like(color, dtype=np.float64)
    dirs = cam.directions(pixel_centres(w, h)).reshape(h, w, 3)
    for y in range(h):
        for x in range(w):
            d = float(depth[y, x])
            point = cam.position + min(d, FAR) * dirs[y, x]
            total, acc = 1.0, color[y, x].astype(np.float64)
            for k, (e_cam, e_depth, e_color) in enumerate(earlier):
                p = e_cam.rotation.T @ (point - e_cam.position)
                if p[2] >= 0.0:
                    continue  # behind the earlier eye
                qx = (p[0] / -p[2] - e_cam.tan_left) * w / (e_cam.tan_right - e_cam.tan_left)
                qy = (e_cam.tan_up - p[1] / -p[2]) * h / (e_cam.tan_up - e_cam.tan_down)
                if not (0.0 <= qx < w and 0.0 <= qy < h):
                    continue
                seen, dist = float(e_depth[int(qy), int(qx)]), float(np.linalg.norm(p))
                if not (math.isinf(seen) if math.isinf(d) else abs(seen - dist) <= rel_depth * dist):
                    continue
                fx, fy = qx - 0.5, qy - 0.5
                x0, y0 = math.floor(fx), math.floor(fy)
                ax, ay = fx - x0, fy - y0
                xs = [min(max(x0 + i, 0), w - 1) for i in (0, 1)]
                ys = [min(max(y0 + i, 0), h - 1) for i in (0, 1)]
                rgb = sum(
                    wx * wy * e_color[ys[j], xs[i]].astype(np.float64)
                    for i, wx in ((0, 1 - ax), (1, ax))
                    for j, wy in ((0, 1 - ay), (1, ay))
                )
                weight = (1.0 - float(alpha[y, x])) ** (k + 1)
                total, acc = total + weight, acc + weight * rgb
            out[y, x] = acc / total
    return out


def test_kim21_smoothing_back_projects_into_turned_and_moved_cameras_as_by_hand():
    """Earlier frames of turned and moved cameras: pixels land between texels, off the image and, for a camera
    turned half way round, behind it; the kernels' passes (footprints, then the depth test and the blend) give
    the closed form computed pixel by pixel."""
    cam = camera(width=40, height=30)
    rng = np.random.default_rng(5)
    depth = rng.uniform(2.0, 2.2, (30, 40)).astype(np.float32)
    depth[:6] = np.inf  # sky: misses match misses
    depth[20:, :10] = 0.5  # a near surface that moved cameras see elsewhere
    alpha = rng.uniform(0.0, 0.9, (30, 40)).astype(np.float32)
    poses = [
        Pose.looking((0.01, 1.6, 0.0), yaw_deg=3.0),
        Pose.looking((0.0, 1.61, 0.02), yaw_deg=-8.0, pitch_deg=4.0),
        Pose.looking((0.0, 1.6, 0.0), yaw_deg=20.0),
        Pose.looking((0.0, 1.6, 0.0), yaw_deg=150.0),
    ]
    history, earlier = History(4), []
    for pose in reversed(poses):  # oldest first
        e_cam = EyeCamera.for_eye(get_profile("rift_s").with_resolution(40, 30), pose)
        e_depth = rng.uniform(2.0, 2.2, (30, 40)).astype(np.float32)
        e_depth[:8] = np.inf
        e_color = rng.random((30, 40, 3), dtype=np.float32)
        history.push(e_cam, e_depth, e_color)
        earlier.insert(0, (e_cam, e_depth, e_color))
    color = rng.random((30, 40, 3), dtype=np.float32)
    image = exponential_smoothing(cam, depth, color, alpha, history, 4, 0.05)
    expected = _smoothed_by_hand(cam, depth, color, alpha, earlier, 0.05)
    assert not np.allclose(image, color, atol=1e-3)  # earlier frames count
    np.testing.assert_allclose(image, expected, atol=2e-5)


# -- smith2013 section 3.2.1: refresh cycle groups --


@pytest.mark.parametrize("order", ["horizontal", "serpentine", "scattered"])
def test_each_peripheral_block_is_refreshed_exactly_once_per_cycle(order):
    params = RrmParams(order=order)
    phase = refresh_phase(61, 23, params)  # sizes that are not multiples of the group
    n = params.cycle
    assert n == 12
    counts = sum((phase == f % n).astype(int) for f in range(5, 5 + n))
    assert np.all(counts == 1)
    # a block is refreshed as a whole: its pixels share a phase
    for x0 in range(0, 60, params.block):
        assert np.all(phase[:, x0 : x0 + params.block] == phase[:, x0 : x0 + 1])


def test_refresh_orders_differ_in_sequence():
    h, s, sc = (visit_order(3, 4, o) for o in ("horizontal", "serpentine", "scattered"))
    assert list(h) == list(range(12))
    assert list(s[:6]) == [0, 1, 2, 5, 4, 3]
    assert sorted(sc) == list(range(12)) and list(sc[:3]) != [0, 1, 2]
    # scattered: consecutive refreshes are never neighbours in the group
    rows, cols = sc // 3, sc % 3
    assert np.all(np.abs(np.diff(rows)) + np.abs(np.diff(cols)) > 1)


def _waits(schedule_of, cycles, width=61, height=23, start=0):
    """Replays frames start.. with group_w cycles[i] on frame start + i; returns each pixel's longest wait between
    two refreshes and the pixels' last refresh, following schedule_of(frame, width, params)'s phase."""
    last, longest = np.full((height, width), -1), np.zeros((height, width), int)
    for i, group_w in enumerate(cycles):
        frame, params = start + i, RrmParams(group_w=group_w)
        refreshed = refresh_phase(width, height, params) == schedule_of(frame, width, params)
        waited = refreshed & (last >= 0)
        longest[waited] = np.maximum(longest[waited], frame - last[waited])
        last[refreshed] = frame
    return longest, last


@pytest.mark.parametrize("start", [0, 7, 1000])
def test_while_n_holds_the_schedule_is_frame_mod_n(start):
    schedule = RefreshSchedule()
    for frame in range(start, start + 40):
        params = RrmParams(order="scattered", group_w=5)
        assert schedule.phase(frame, 61, params) == frame % params.cycle
        assert schedule.phase(frame, 61, params) == frame % params.cycle  # the same frame again: the same phase


def test_after_a_change_of_n_every_pixel_is_refreshed_within_the_new_n_frames():
    """smith2013 section 3.2.1's bound, N frames, holds again once the new N is held for N frames, and no pixel
    waits longer than the N before a change and the N after."""
    cycles = [3] * 30 + [4] * 16 + [2] * 8 + [5] * 20 + [1] * 4 + [5] * 20  # each N held for N frames
    changes = np.flatnonzero(np.diff(cycles)) + 1
    for at in changes:
        replay = RefreshSchedule()
        _, last = _waits(replay.phase, cycles[: at + 4 * cycles[at]])
        assert np.all(last >= at), at
    longest, _ = _waits(RefreshSchedule().phase, cycles)
    assert longest.max() <= max(4 * (cycles[at - 1] + cycles[at]) - 1 for at in changes)


def test_waits_stay_near_the_largest_n_when_n_moves_every_few_frames():
    """The budget controller may move N every frame or two; frame mod N then leaves pixels waiting for the sum
    of the cycles they crossed."""
    rng = np.random.default_rng(4)
    cycles = np.repeat(rng.integers(1, 6, 120), rng.integers(1, 12, 120))  # N from 4 to 20, held 1-11 frames
    longest, last = _waits(RefreshSchedule().phase, cycles)
    longest_mod, _ = _waits(lambda frame, width, params: frame % params.cycle, cycles)
    assert np.all(last >= len(cycles) - 20)
    assert longest.max() <= 30 < 40 < longest_mod.max()


def test_fixation_filter_smooths_jitter_and_follows_saccades():
    f = FixationFilter(alpha=0.3, saccade_deg=3.0)
    rng = np.random.default_rng(0)
    raw = [gaze_direction(*rng.normal(0.0, 0.4, 2)) for _ in range(200)]
    out = np.array([f(g) for g in raw])
    spread = lambda v: np.degrees(np.arccos(np.clip(v @ [0, 0, -1], -1, 1))).std()  # noqa: E731
    assert spread(out[20:]) < 0.6 * spread(np.array(raw[20:]))
    jump = gaze_direction(10.0, 0.0)
    np.testing.assert_allclose(f(jump), jump)  # a saccade is followed at once


def test_vergence_depth():
    left, right = np.array([-0.032, 0.0, 0.0]), np.array([0.032, 0.0, 0.0])
    target = np.array([0.1, 0.05, -1.5])
    dl, dr = (target - left) / np.linalg.norm(target - left), (target - right) / np.linalg.norm(target - right)
    assert vergence_depth(left, dl, right, dr) == pytest.approx(np.linalg.norm(target), rel=1e-9)
    forward = np.array([0.0, 0.0, -1.0])
    assert vergence_depth(left, forward, right, forward) is None  # parallel: at infinity


# -- weier2018 section 3.2: circles of confusion --


def test_coc_is_zero_inside_the_focus_range_and_grows_outside():
    focus = 1.5
    d_n, d_f, f_n, f_f = focal_lengths(focus, 0.2)
    assert (d_n, d_f) == pytest.approx((1300.0, 1700.0))
    k, e = DOF_PRESETS["medium"]
    for g in np.linspace(d_n, d_f, 9):
        assert circle_of_confusion(g, d_n, d_f, f_n, f_f, k, e) == 0.0
    near = [circle_of_confusion(g, d_n, d_f, f_n, f_f, k, e) for g in (1299.0, 1000.0, 600.0, 300.0)]
    far = [circle_of_confusion(g, d_n, d_f, f_n, f_f, k, e) for g in (1701.0, 3000.0, 8000.0, math.inf)]
    assert all(c > 0 for c in near) and np.all(np.diff(near) > 0)  # near field: positive, growing
    assert all(c < 0 for c in far) and np.all(np.diff(far) < 0)  # far field: negative, growing in size
    assert abs(near[0]) < 0.05 and abs(far[0]) < 0.05  # continuous at the range's ends


def test_coc_presets_blur_2_5_and_10_pixels_at_rift_s():
    """As docs/methods.md says: a point at 6 m while fixating 0.75 m, at rift_s's own pixel density."""
    ppd = sum(pixels_per_degree(camera())) / 2
    assert REFERENCE_PPD == pytest.approx(ppd, abs=0.01)
    depth = np.array([[0.75, 6.0]])
    sizes = [abs(coc_map(depth, 0.75, DOF_PRESETS[p], ppd)[0, 1]) for p in ("weak", "medium", "strong")]
    np.testing.assert_allclose(sizes, [2.0, 5.0, 10.0], rtol=0.05)
    assert coc_map(depth, 0.75, DOF_PRESETS["medium"], ppd)[0, 0] == 0.0
    half = abs(coc_map(depth, 0.75, DOF_PRESETS["medium"], ppd / 2)[0, 1])  # the same angle on a coarser display
    assert half == pytest.approx(sizes[1] / 2)
