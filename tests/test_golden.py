"""Golden images: every method's frames on the built-in head path, pinned so that speed never silently
changes results.

Each case renders 8 frames of the left eye at 96x108 (sim-cpu optics, seed 0) along the built-in head path
(head sway, fixations and saccades), so the temporal stages run on moving views, and compares frames 3 and
7 with the stored ones. Tolerance: PSNR >= 40 dB over the image (peak 1) and at least 99% of pixels within
1e-3 in every channel; a kernel that reorders float arithmetic stays well inside it, a changed sample set,
filter or blend does not. `HMDRT_UPDATE_GOLDEN=1 pytest tests/test_golden.py` rewrites the files after a
change that is meant to alter the images (say why in the commit), and writes those of a new case.

The cases are the registered methods' own (registry.golden_cases, from each method's Checks): a method registered
without its golden images fails here with "no golden image for method ...", and an image no method declares with
"... belongs to no registered method".
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from hmdrt.evaluate.quality import psnr
from hmdrt.foveation import make_method
from hmdrt.foveation.registry import golden_cases
from hmdrt.optics import get_profile
from hmdrt.scene import load_scene
from hmdrt.trace.integrator import Whitted
from hmdrt.views import builtin_path, render_frames
from tests.helpers import DATA

GOLDEN = DATA / "golden"
FRAMES, KEPT = 8, (3, 7)
CASES = golden_cases()


def golden_frames(scene: str, spec: str) -> list[np.ndarray]:
    """Frames KEPT of the case, rendered now."""
    profile = get_profile("sim-cpu").with_resolution(96, 108)
    loaded = load_scene(scene)
    inputs = builtin_path(FRAMES, profile.period_ns, loaded.start)
    with Whitted(loaded) as tracer:
        method = make_method(spec, tracer)
        images = [images[0].copy() for _, images, _ in render_frames(method, profile, inputs, ("left",))]
    return [images[k] for k in KEPT]


def case_file(scene: str, spec: str):
    return GOLDEN / f"{scene}_{spec.replace('?', '_').replace('=', '-')}.npz"


def missing_golden() -> list[str]:
    """What the registered methods' golden cases lack, one line each: an image not pinned, or one no case is for."""
    cases = golden_cases()
    missing = [
        f"no golden image for method {spec} on {scene} (tests/data/golden/{case_file(scene, spec).name}): pin it with "
        f"HMDRT_UPDATE_GOLDEN=1 pytest 'tests/test_golden.py::test_method_matches_its_golden_frames[{scene}-{spec}]'"
        for scene, spec in cases
        if not case_file(scene, spec).exists()
    ]
    pinned = {case_file(scene, spec).name for scene, spec in cases}
    stale = [
        f"golden image {path.name} belongs to no registered method (registry.golden_cases)"
        for path in sorted(GOLDEN.glob("*.npz"))
        if path.name not in pinned
    ]
    return missing + stale


def test_every_registered_method_has_its_golden_images() -> None:
    assert not missing_golden(), "\n".join(missing_golden())


@pytest.mark.parametrize(("scene", "spec"), CASES, ids=[f"{s}-{m}" for s, m in CASES])
def test_method_matches_its_golden_frames(scene: str, spec: str) -> None:
    path = case_file(scene, spec)
    updating = bool(os.environ.get("HMDRT_UPDATE_GOLDEN"))
    if not (updating or path.exists()):
        pytest.fail(f"no golden image for method {spec} on {scene}: {path} (HMDRT_UPDATE_GOLDEN=1 writes it)")
    frames = golden_frames(scene, spec)
    if updating:
        GOLDEN.mkdir(exist_ok=True)
        np.savez_compressed(path, **{f"frame_{k}": f for k, f in zip(KEPT, frames, strict=True)})
    stored = np.load(path)
    for k, frame in zip(KEPT, frames, strict=True):
        want = stored[f"frame_{k}"]
        assert frame.shape == want.shape
        close = (np.abs(frame - want) <= 1e-3).all(axis=-1).mean()
        assert psnr(frame, want) >= 40.0, f"frame {k}: {psnr(frame, want):.1f} dB against the golden frame"
        assert close >= 0.99, f"frame {k}: only {close:.2%} of pixels within 1e-3 of the golden frame"


def test_golden_check_catches_a_changed_image() -> None:
    """The tolerance is tight enough to fail on a small change: a 1% brighter frame or a blurred one."""
    frame = golden_frames("whitted", "full")[0]
    brighter = frame * 1.01
    blurred = (frame + np.roll(frame, 1, axis=1)) / 2
    for changed in (brighter, blurred):
        close = (np.abs(changed - frame) <= 1e-3).all(axis=-1).mean()
        assert close < 0.99 or psnr(changed, frame) < 40.0
