"""bench/own_rays.py: bare embreex on the rays a method's last frame traced, against the view's every pixel; the
recorder of those rays leaves the tracer as it was."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted
from tests.test_registry import bench_module


@pytest.fixture(scope="module")
def own_rays():
    return bench_module("own_rays")


def test_the_recorder_keeps_each_calls_samples_and_puts_the_tracer_back(own_rays):
    references = bench_module("references")
    scene = load_scene("whitted")
    camera = references.left_eye_requests(scene, get_profile("sim-cpu"), 1, None)[0].camera
    xy = np.array([[0.5, 0.5], [10.25, 20.75]], np.float32)
    original = Whitted.trace_samples
    calls: list[np.ndarray] = []
    undo = own_rays.record_samples(calls)
    assert Whitted.trace_samples is not original
    try:
        with Whitted(scene, 1) as tracer:
            out = tracer.trace_samples(camera, xy, np.arange(2), FrameStats())
    finally:
        undo()
    assert Whitted.trace_samples is original
    assert out.shape == (2, 3)
    assert len(calls) == 1 and np.array_equal(calls[0], xy)


def test_bare_rays_through_given_pixels_build_their_own_secondary_and_shadow_rays(own_rays):
    references = bench_module("references")
    scene, profile = load_scene("whitted"), get_profile("sim-cpu")
    camera = references.left_eye_requests(scene, profile, 1, None)[0].camera
    every = references.BareRays(scene, camera, 1)
    xy = np.array([[x + 0.5, y + 0.5] for y in range(0, profile.height, 4) for x in range(0, profile.width, 4)])
    some = references.BareRays(scene, camera, 1, xy.astype(np.float32))
    try:
        assert len(every.kinds["primary"].dirs) == profile.width * profile.height
        assert len(some.kinds["primary"].dirs) == len(xy)
        # every 16th pixel's camera ray is the view's ray through that pixel
        index = ((xy[:, 1] - 0.5) * profile.width + xy[:, 0] - 0.5).astype(int)
        np.testing.assert_allclose(some.kinds["primary"].dirs, every.kinds["primary"].dirs[index], atol=1e-6)
        assert 0 < len(some.kinds["shadow"].dirs) < len(every.kinds["shadow"].dirs)
        assert some.rate("primary") > 0
    finally:
        every.close()
        some.close()


def test_the_bench_prints_each_methods_rates_and_its_frame_over_both_floors(own_rays, monkeypatch, capsys):
    argv = ["own_rays.py", "--profile", "sim-cpu", "--frames", "3", "--warmup", "1", "--rounds", "1"]
    monkeypatch.setattr(sys, "argv", [*argv, "--methods", "full", "rrm"])
    own_rays.main()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith(
        "whitted at sim-cpu (192x216, one eye), still view, gaze 0,0: each method's rays of frame 3"
    )
    assert lines[1].startswith("  the view's rays, Mrays/s: primary ")
    rows = {line.split()[0]: line.split() for line in lines[3:5]}
    assert int(rows["full"][1].replace(",", "")) == 192 * 216  # full traces every pixel once
    assert 0 < int(rows["rrm"][1].replace(",", "")) < 192 * 216
    floors = {line.split()[0]: line.split() for line in lines[-2:]}
    for spec in ("full", "rrm"):
        frame, mix, over_mix, own, over_own = (float(v.rstrip("x")) for v in floors[spec][1:6])
        assert mix > 0 and own > 0
        for floor, over in ((mix, over_mix), (own, over_own)):  # the ratio of the printed figures, to their rounding
            assert (frame - 0.05) / (floor + 0.05) - 0.005 <= over <= (frame + 0.05) / (floor - 0.05) + 0.005
