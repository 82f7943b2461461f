"""hmdrt eval's scores: band metrics (PSNR, SSIM, flicker) in display and linear space, the Pareto front and
the summary's pick, and the ground-truth cache."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hmdrt.evaluate.quality import BANDS, BandScores, band_psnr, psnr, srgb_encode, ssim_map, to_space
from hmdrt.evaluate.runner import pareto_front, summarise
from hmdrt.evaluate.truth import TruthCache, scene_digest
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.present.encode import linear_to_srgb8
from hmdrt.scene import load_scene
from hmdrt.spatial import Pose
from hmdrt.trace.integrator import Whitted

RNG = np.random.default_rng(7)


def test_ssim_is_one_for_identical_images_and_matches_a_direct_window_sum_inside():
    a = RNG.random((40, 48, 3), dtype=np.float32)
    b = np.clip(a + RNG.normal(0, 0.1, a.shape).astype(np.float32), 0, 1)
    assert np.allclose(ssim_map(a, a), 1.0)
    # one interior pixel by the definition: 11 x 11 Gaussian window, sigma 1.5, on Rec. 709 luminance
    y, x = 20, 24
    k = np.exp(-0.5 * (np.arange(-5, 6) / 1.5) ** 2)
    w = np.outer(k, k) / np.outer(k, k).sum()
    la = (a @ [0.2126, 0.7152, 0.0722])[y - 5 : y + 6, x - 5 : x + 6]
    lb = (b @ [0.2126, 0.7152, 0.0722])[y - 5 : y + 6, x - 5 : x + 6]
    ma, mb = (w * la).sum(), (w * lb).sum()
    va, vb, cab = (w * la * la).sum() - ma**2, (w * lb * lb).sum() - mb**2, (w * la * lb).sum() - ma * mb
    c1, c2 = 0.01**2, 0.03**2
    expected = (2 * ma * mb + c1) * (2 * cab + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
    assert ssim_map(a, b)[y, x] == pytest.approx(expected, abs=1e-6)
    assert expected < 0.99  # the noise is seen


def test_band_scores_pool_the_squared_error_over_frames_and_measure_flicker_beyond_the_truths():
    truth = np.full((30, 40, 3), 0.5, dtype=np.float32)
    eccentricity = np.tile(np.linspace(0, 40, 40, dtype=np.float32), (30, 1))
    scores = BandScores("linear")
    scores.add(truth + 0.1, truth, eccentricity)  # squared error 0.01
    scores.add(truth - 0.1, truth, eccentricity)  # squared error 0.01, and a change of 0.2 from the last frame
    scores.add(truth + 0.1, truth, eccentricity)
    result = scores.result()
    for band in (*BANDS, "image"):
        assert result[f"psnr_{band}"] == pytest.approx(20.0, abs=1e-3)  # 10 log10(1 / 0.01)
        assert result[f"flicker_{band}"] == pytest.approx(0.2, abs=1e-6)  # the truth is steady
    steady = BandScores("linear")
    for _ in range(3):
        steady.add(truth + 0.1, truth, eccentricity)
    assert steady.result()["flicker_image"] == pytest.approx(0.0, abs=1e-7)
    assert steady.result()["ssim_image"] == pytest.approx(ssim_map(truth + 0.1, truth).mean(), abs=1e-9)
    empty = BandScores()
    empty.add(truth, truth, np.zeros((30, 40), dtype=np.float32))  # every pixel in the fovea
    assert empty.result()["psnr_fovea"] == math.inf and empty.result()["psnr_parafovea"] is None


@pytest.mark.parametrize("space", ["srgb", "linear"])
def test_flicker_is_the_change_that_differs_from_the_truths_so_a_frozen_image_is_not_steadier(space):
    eccentricity = np.tile(np.linspace(0, 40, 40, dtype=np.float32), (30, 1))
    truths = [np.full((30, 40, 3), v, dtype=np.float32) for v in (0.2, 0.4, 0.3, 0.6)]  # the scene changes
    frozen, itself = BandScores(space), BandScores(space)
    for truth in truths:
        frozen.add(truths[0], truth, eccentricity)  # a method that never updates its image
        itself.add(truth, truth, eccentricity)
    for band in (*BANDS, "image"):
        assert frozen.result()[f"flicker_{band}"] > 0.05
        assert itself.result()[f"flicker_{band}"] == 0.0
    encoded = [to_space(t, space)[0, 0, 0] for t in truths]
    expected = np.mean(np.abs(np.diff(encoded)))  # the frozen image misses every change of the truth
    assert frozen.result()["flicker_image"] == pytest.approx(expected, rel=1e-5)


def _srgb(x: float) -> float:
    """IEC 61966-2-1's encoding, written out."""
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def test_scores_are_of_display_encoded_images_by_default_and_of_linear_radiance_on_request():
    values = np.array([-0.5, 0.0, 0.002, 0.0031308, 0.01, 0.18, 0.5, 0.99, 1.0, 4.0], dtype=np.float32)
    assert srgb_encode(values) == pytest.approx([_srgb(min(max(v, 0.0), 1.0)) for v in values], abs=1e-6)
    srgb8 = linear_to_srgb8(np.tile(values, (1, 1, 1)).reshape(1, -1, 1).repeat(3, axis=2))[0, :, 0]
    assert np.abs(srgb_encode(values) * 255 - srgb8).max() <= 0.5 + 1e-3  # the display's 8 bits, unquantised
    truth = np.full((30, 40, 3), 0.02, dtype=np.float32)
    image = truth + np.float32(0.01)
    eccentricity = np.zeros((30, 40), dtype=np.float32)
    scores = {space: BandScores(space) for space in ("srgb", "linear")}
    for s in scores.values():
        s.add(image, truth, eccentricity)
    linear = -10 * math.log10(0.01**2)
    displayed = -10 * math.log10((_srgb(0.03) - _srgb(0.02)) ** 2)
    assert BandScores().space == "srgb"
    assert scores["linear"].result()["psnr_fovea"] == pytest.approx(linear, abs=1e-3)
    assert scores["srgb"].result()["psnr_fovea"] == pytest.approx(displayed, abs=1e-3)
    assert displayed < linear - 10  # an error in the dark is larger on the display than in radiance
    # the module's functions score whatever space they are given
    assert psnr(to_space(image, "srgb"), to_space(truth, "srgb")) == pytest.approx(displayed, abs=1e-3)
    assert band_psnr(image, truth, eccentricity)["fovea"] == pytest.approx(linear, abs=1e-3)


def test_pareto_front_keeps_only_points_no_other_beats():
    points = [(10.0, 30.0), (5.0, 30.0), (5.0, 25.0), (20.0, 40.0), (20.0, 35.0), (1.0, None), (5.0, 30.0)]
    assert pareto_front(points) == [False, True, False, True, False, False, True]


def _summary_row(label, ms, psnr, baseline="full", method=None, base=(40.0, 30.0)):
    return {
        "scene": "s",
        "profile": "p",
        "trace": "t",
        "method": method or label.partition("?")[0],
        "params": label,
        "label": label,
        "ms_per_frame": ms,
        "psnr_fovea": psnr,
        "pareto": False,
        "baseline": baseline,
        "speedup_vs_baseline": base[0] / ms,
        "psnr_fovea_vs_baseline": psnr - base[1],
    }


def test_summary_picks_the_fastest_foveated_cell_at_least_as_sharp_as_its_baseline():
    selective = (20.0, 40.0)
    rows = [
        _summary_row("full", 40.0, 30.0),
        _summary_row("rrm?a=1", 5.0, 29.0),  # faster, but blurrier than full
        _summary_row("kim21", 10.0, 31.0),
        _summary_row("weier16", 12.0, 30.0),
        _summary_row("regular?spp=4", 9.0, 32.0),  # a reference, never the best foveated cell
        _summary_row("Selective", 20.0, 40.0, method="kim21"),
        _summary_row("Sel_Fov", 30.0, 41.0, baseline="Selective", method="kim21", base=selective),  # slower than full
        _summary_row("Sel_Fov fast", 15.0, 39.0, baseline="Selective", method="kim21", base=selective),
    ]
    by_full, by_selective = summarise(rows)
    assert by_full["baseline"] == "full" and by_full["baseline_psnr_fovea"] == 30.0 and by_full["baseline_ms"] == 40.0
    assert by_full["best"] == "kim21" and by_full["best_speedup"] == 4.0 and by_full["best_psnr_fovea_delta"] == 1.0
    assert by_selective["baseline"] == "Selective" and by_selective["best"] == "Sel_Fov"  # the fast one is blurrier
    assert by_selective["best_speedup"] == pytest.approx(20.0 / 30.0) and by_selective["best_psnr_fovea_delta"] == 1.0
    [alone] = summarise([_summary_row("rrm", 5.0, 29.0, baseline=None)])
    assert alone["baseline"] is None and alone["best"] is None


def test_truth_cache_renders_a_view_once_and_reads_it_back(tmp_path):
    scene = load_scene("whitted")
    profile = get_profile("sim-cpu").with_resolution_text("32x36")
    camera = EyeCamera.for_eye(profile, scene.start)
    moved = EyeCamera.for_eye(profile, Pose(scene.start.position + [0.0, 0.1, 0.0], scene.start.orientation))
    with Whitted(scene) as tracer:
        cache = TruthCache(tmp_path, spp=4)
        first = cache.get(tracer, scene_digest(scene), camera)
        again = cache.get(tracer, scene_digest(scene), camera)
        other = cache.get(tracer, scene_digest(scene), moved)
        assert (cache.rendered, cache.read) == (2, 1)
        assert np.array_equal(first, again) and not np.array_equal(first, other)
        assert first.shape == (36, 32, 3) and np.isfinite(first).all()
        assert sorted(p.suffix for p in tmp_path.iterdir()) == [".npy", ".npy"]  # no temporary file left
        next(tmp_path.iterdir()).write_bytes(b"truncated")
        fresh = TruthCache(tmp_path, spp=4)
        fresh.get(tracer, scene_digest(scene), camera)
        fresh.get(tracer, scene_digest(scene), moved)
        assert (fresh.rendered, fresh.read) == (1, 1)  # the damaged file is rendered again, the other read
        assert TruthCache(tmp_path, spp=8).key(scene_digest(scene), camera) != cache.key(scene_digest(scene), camera)


def test_scene_digest_follows_the_scene_content():
    assert scene_digest(load_scene("whitted")) == scene_digest(load_scene("whitted"))
    assert scene_digest(load_scene("whitted")) != scene_digest(load_scene("tunnel_maps"))
