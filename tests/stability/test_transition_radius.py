"""Numerical stability at the edges: weier2018 equation (1), the transition radius of the sampling tables."""

from __future__ import annotations

from decimal import Decimal, localcontext

import numpy as np
import pytest

from hmdrt.foveation.stages.sampling import (
    transition_radius,
)


def _printed_equation_1(u: float, p: float, digits: int = 60) -> float:
    """Equation (1) as printed, in 60-digit decimal arithmetic: the reference away from p = 1."""
    with localcontext() as ctx:
        ctx.prec = digits
        du, dp = Decimal(u), Decimal(p)
        return float((((dp * dp - 1) * du + 1).sqrt() - 1) / (dp - 1))


@pytest.mark.parametrize("p_min", [0.0, 1e-300, 0.05, 0.5, 1.0 - 1e-12, 1.0])
def test_equation_1_at_u_0_and_1_gives_exactly_r0_and_r1(p_min):
    r = transition_radius(np.array([0.0, 1.0]), 10.0, 20.0, p_min)
    assert r[0] == 10.0 and r[1] == pytest.approx(20.0, abs=1e-12)


def test_equation_1_as_p_min_tends_to_1_follows_the_series_instead_of_0_over_0():
    u = np.linspace(0.0, 1.0, 21)
    np.testing.assert_array_equal(transition_radius(u, 0.0, 1.0, 1.0), u)  # the limit p = 1: uniform
    for eps in (1e-2, 1e-4, 1e-8, 1e-12, 1e-15):
        x = transition_radius(u, 0.0, 1.0, 1.0 - eps)
        # x = u - eps u (1 - u) / 2 - eps^2 u^2 (1 - u) / 2 + O(eps^3)
        series = u - eps * u * (1 - u) / 2 - eps**2 * u * u * (1 - u) / 2
        np.testing.assert_allclose(x, series, atol=eps**3 + 4e-16)
        if eps >= 1e-8:
            reference = [_printed_equation_1(v, 1.0 - eps) for v in u]
            np.testing.assert_allclose(x, reference, atol=4e-16)


def test_equation_1_as_p_min_tends_to_0_is_the_inverse_cdf_of_a_linear_ramp():
    u = np.linspace(0.0, 1.0, 101)
    for p in (0.0, 1e-300, 1e-12):
        x = transition_radius(u, 0.0, 1.0, p)
        np.testing.assert_allclose(x, 1.0 - np.sqrt(1.0 - u), atol=1e-11)  # F(x) = 2x - x^2 inverted
    assert np.all(np.diff(transition_radius(u, 5.0, 10.0, 0.0)) > 0)  # monotone up to u = 1 (infinite slope)
