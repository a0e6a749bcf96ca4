"""The base's planar pose helpers agree with each other and with a rotation matrix."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from mmctl.model.planar import base_to_world, point_to_world, rot_z, world_to_base

finite = st.floats(-1e3, 1e3, allow_nan=False)
angles = st.floats(-4 * math.pi, 4 * math.pi, allow_nan=False)


@given(st.tuples(finite, finite, finite), angles)
def test_world_and_base_are_inverse_rotations_about_z(v: tuple[float, float, float],
                                                      yaw: float) -> None:
    a = np.array(v)
    w = base_to_world(a, yaw)
    np.testing.assert_allclose(w, rot_z(yaw) @ a, atol=1e-9)
    np.testing.assert_allclose(world_to_base(w, yaw), a, atol=1e-9)
    assert w[2] == a[2] and math.isclose(np.linalg.norm(w), np.linalg.norm(a), abs_tol=1e-9)


@given(finite, finite, angles, st.tuples(finite, finite, finite))
def test_a_point_moves_with_the_base(x: float, y: float, yaw: float,
                                     p: tuple[float, float, float]) -> None:
    np.testing.assert_allclose(point_to_world(x, y, yaw, p),
                               np.array([x, y, 0.0]) + base_to_world(p, yaw), atol=1e-9)


def test_a_quarter_turn() -> None:
    np.testing.assert_allclose(base_to_world([1.0, 0.0, 0.5], math.pi / 2), [0.0, 1.0, 0.5],
                               atol=1e-15)
    np.testing.assert_allclose(world_to_base([0.0, 1.0, 0.5], math.pi / 2), [1.0, 0.0, 0.5],
                               atol=1e-15)
