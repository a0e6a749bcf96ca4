"""Mecanum kinematics: round trip, signs, direction-keeping scaling."""

from __future__ import annotations

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from mmctl.config.base import MecanumConfig
from mmctl.config.schema import build
from mmctl.control.mecanum import twist_to_wheels, wheel_matrix, wheel_scale, wheels_to_twist

GEOM = build(MecanumConfig, {})
finite = st.floats(-3.0, 3.0, allow_nan=False)


@given(finite, finite, finite)
def test_twist_wheels_twist_is_identity(vx: float, vy: float, wz: float) -> None:
    t = np.array([vx, vy, wz])
    assert np.allclose(wheels_to_twist(GEOM, twist_to_wheels(GEOM, t)), t, atol=1e-12)


def test_spec_formula() -> None:
    r, ell = 0.127, 0.21528 + 0.2690
    vx, vy, wz = 0.3, -0.2, 0.5
    expected = np.array(
        [(vx - vy - ell * wz) / r, (vx + vy + ell * wz) / r, (vx + vy - ell * wz) / r, (vx - vy + ell * wz) / r]
    )
    assert np.allclose(twist_to_wheels(GEOM, np.array([vx, vy, wz])), expected)
    assert wheel_matrix(GEOM).shape == (4, 3)


@given(finite, finite, finite, st.floats(0.5, 30.0))
def test_scaling_keeps_direction_and_bound(vx: float, vy: float, wz: float, limit: float) -> None:
    t = np.array([vx, vy, wz]) * 10.0
    w = twist_to_wheels(GEOM, t)
    s = wheel_scale(w, limit)
    assert 0.0 <= s <= 1.0
    assert np.max(np.abs(w * s)) <= limit * (1 + 1e-12)
    scaled = wheels_to_twist(GEOM, w * s)
    assert np.allclose(scaled, s * t, atol=1e-9)
