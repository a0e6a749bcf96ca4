"""Exact ZOH admittance against the analytic first-order response."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mmctl.config import default_config
from mmctl.control.admittance import Admittance


def test_step_response_matches_the_analytic_first_order_response() -> None:
    adm = Admittance.from_config(default_config().admittance)  # M = 4, B = 75 (paper)
    f = np.array([20.0, -10.0, 5.0, 1.0, -2.0, 0.5])
    T = 0.002
    v = np.zeros(6)
    for k in range(1, 501):
        v = adm.step(v, f, T)
        analytic = f / 75.0 * (1.0 - np.exp(-75.0 * k * T / 4.0))
        assert np.allclose(v, analytic, rtol=1e-12, atol=1e-15)
    assert np.allclose(v, f / 75.0, rtol=1e-6)  # settled after 1 s (19 time constants)


@given(
    st.lists(st.floats(0.1, 50.0), min_size=6, max_size=6),
    st.lists(st.floats(1.0, 500.0), min_size=6, max_size=6),
    st.floats(1e-4, 0.5),
    st.floats(-100.0, 100.0),
)
def test_any_period_is_exact_and_stable(mass, damping, T, f0) -> None:
    """Two steps of T equal one step of 2T for a held force, and |a| < 1 always."""
    adm = Admittance(np.array(mass), np.array(damping))
    f = np.full(6, f0)
    v0 = np.linspace(-1, 1, 6)
    two = adm.step(adm.step(v0, f, T), f, T)
    one = adm.step(v0, f, 2 * T)
    assert np.allclose(two, one, rtol=1e-9, atol=1e-12)
    a, _ = adm.coefficients(T)
    assert np.all((a >= 0.0) & (a < 1.0))


def test_rejects_non_positive_parameters() -> None:
    with pytest.raises(ValueError, match="> 0"):
        Admittance(np.full(6, 4.0), np.array([75.0, 75, 0, 75, 75, 75]))
    adm = Admittance(np.full(6, 4.0), np.full(6, 75.0))
    assert np.allclose(adm.time_constant(), 4.0 / 75.0)
    assert math.isclose(adm.coefficients(0.002)[0][0], math.exp(-75 * 0.002 / 4))
