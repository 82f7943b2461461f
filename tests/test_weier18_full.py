"""weier2018 section 4.1's full mode, the baseline of its Table 1: every pixel sampled, no temporal anti-aliasing,
and the same circles of confusion, depth-of-field filter and contrast-enhancing combine as the foveated mode."""

from __future__ import annotations

import numpy as np

from hmdrt.foveation import make_method
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.trace.integrator import Whitted
from hmdrt.views import builtin_path, eye_cameras, render_frames

PROFILE = get_profile("sim-cpu").with_resolution(96, 108)


def frames(spec: str, count: int):
    scene = load_scene("whitted")
    inputs = builtin_path(count, PROFILE.period_ns, scene.start)
    with Whitted(scene) as tracer:
        method = make_method(spec, tracer)
        out = [(images[0].copy(), stats) for _, images, stats in render_frames(method, PROFILE, inputs, ("left",))]
    return method, inputs, out


def test_full_mode_samples_every_pixel_and_runs_no_taa():
    method, _, out = frames("weier18?mode=full", 4)
    assert method.warmup_frames == 0
    for image, stats in out:
        assert np.isfinite(image).all()
        assert stats.metrics["sample_fraction"] == 1.0
        assert stats.rays["primary"] == PROFILE.width * PROFILE.height
        assert not any(stage.split("/")[0] == "taa" for stage in stats.stages_ms), stats.stages_ms
        assert {"coc", "dof_filter", "combine"} <= set(stats.stages_ms)  # the same depth of field and combine
    _, _, foveated = frames("weier18", 4)
    assert "taa" in foveated[-1][1].stages_ms and foveated[-1][1].metrics["sample_fraction"] < 0.6


def test_full_mode_matches_the_foveated_mode_in_the_fovea_before_any_history():
    """Frame 0 keeps no history in either mode, and the fovea is traced whole in both: there the images agree,
    so the two modes share the circles of confusion, the filter and the combine."""
    _, inputs, full = frames("weier18?mode=full", 1)
    _, _, foveated = frames("weier18", 1)
    cam = eye_cameras(PROFILE, inputs[0].pose, ("left",))["left"]
    fovea = cam.eccentricity(inputs[0].gaze["left"]) < 10.0 - 4.0  # r0, less the reach of the central blur
    assert fovea.sum() > 50
    np.testing.assert_allclose(full[0][0][fovea], foveated[0][0][fovea], atol=1e-5)
