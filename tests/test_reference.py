"""The reference renderers: full (one ray per pixel) and regular (N stratified samples per pixel)."""

import numpy as np
import pytest

from hmdrt.errors import ConfigError
from hmdrt.foveation import make_method
from hmdrt.scene import load_scene
from hmdrt.trace.integrator import Whitted
from hmdrt.trace.sampling import grid_shape, jittered_pixels

from .helpers import render


@pytest.mark.parametrize("n,shape", [(36, (6, 6)), (1, (1, 1)), (8, (2, 4)), (5, (1, 5)), (12, (3, 4))])
def test_grid_shape_factors_the_sample_count(n, shape):
    assert grid_shape(n) == shape


def test_jittered_samples_fill_each_stratum_of_each_pixel_once():
    width, rows, spp = 5, 3, 36
    xy = jittered_pixels(width, 10, rows, spp, seed=4).reshape(rows, width, spp, 2)
    for r in range(rows):
        for x in range(width):
            s = xy[r, x]
            assert np.all((s[:, 0] >= x) & (s[:, 0] < x + 1) & (s[:, 1] >= 10 + r) & (s[:, 1] < 11 + r))
            cells = np.floor((s - [x, 10 + r]) * 6).astype(int)
            assert len({tuple(c) for c in cells}) == 36  # one sample in every 6x6 stratum


def test_regular_converges_where_full_aliases():
    """The checkerboard's distant cells alias at 1 spp; 16 and 36 spp agree closely with each other."""
    full, _ = render("whitted", 48, 48)
    r16, _ = render("whitted", 48, 48, method="regular", spp=16)
    r36, _ = render("whitted", 48, 48, method="regular", spp=36)
    err_full = np.abs(full - r36).mean()
    err_16 = np.abs(r16 - r36).mean()
    assert err_16 < 0.5 * err_full
    # the average over the image is preserved by supersampling (a box filter)
    assert abs(r36.mean() - full.mean()) < 0.02


def test_regular_counts_its_rays():
    _, stats = render("tunnel_maps", 16, 12, method="regular", spp=9)
    assert stats.rays["primary"] == 16 * 12 * 9
    assert "resolve" in stats.stages_ms


def test_method_options_are_checked():
    with Whitted(load_scene("whitted")) as tracer:
        with pytest.raises(ConfigError, match="unknown method"):
            make_method("fancy", tracer)
        with pytest.raises(ConfigError, match="unknown field `spp`"):
            make_method("full", tracer, spp=4)
        with pytest.raises(ConfigError, match=">= 1"):
            make_method("regular", tracer, spp=0)
        assert make_method("regular?spp=9", tracer).spp == 9
