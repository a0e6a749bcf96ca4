"""Base command scaling and odometry integration shared by both transports."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mmctl.config.base import MecanumConfig
from mmctl.config.schema import build
from mmctl.control.mecanum import twist_to_wheels, wheel_matrix
from mmctl.transports.base.kinematics import OdometryIntegrator, WheelCommand, wrap_delta

GEOM = build(MecanumConfig, {})
LIMIT = 27.27
speed = st.floats(-20.0, 20.0, allow_nan=False)


@settings(deadline=None)
@given(speed, speed, speed)
def test_command_never_exceeds_the_wheel_limit_and_keeps_direction(
    vx: float, vy: float, wz: float
) -> None:
    wheels, twist = WheelCommand(GEOM, LIMIT)(vx, vy, wz)
    assert np.max(np.abs(wheels)) <= LIMIT * (1 + 1e-12)
    # the wheels realise exactly the returned twist ...
    assert np.allclose(wheels, twist_to_wheels(GEOM, np.array(twist)), atol=1e-9)
    # ... which is the requested one times a factor in (0, 1]
    req = np.array([vx, vy, wz])
    got = np.array(twist)
    if np.linalg.norm(req) > 1e-9:
        s = float(got @ req / (req @ req))
        assert 0.0 < s <= 1.0 + 1e-12
        assert np.allclose(got, s * req, atol=1e-9)
        peak = np.max(np.abs(wheel_matrix(GEOM) @ req))
        if peak <= LIMIT:
            assert s == pytest.approx(1.0)
        else:
            assert np.max(np.abs(wheels)) == pytest.approx(LIMIT)


def test_command_rejects_non_finite() -> None:
    with pytest.raises(ValueError, match="non-finite"):
        WheelCommand(GEOM, LIMIT)(math.nan, 0.0, 0.0)


def test_odometry_straight_line_and_turn_in_place() -> None:
    odo = OdometryIntegrator(GEOM)
    odo.reset(0.0)
    w = wheel_matrix(GEOM)
    for k in range(100):  # 1 m forward in 100 steps
        odo.update(w @ np.array([0.01, 0.0, 0.0]), w @ np.array([1.0, 0.0, 0.0]), k * 0.01)
    o = odo.odometry()
    assert (o.x, o.y, o.yaw) == pytest.approx((1.0, 0.0, 0.0), abs=1e-12)
    assert (o.vx, o.vy, o.wz) == pytest.approx((1.0, 0.0, 0.0))
    assert o.timestamp == pytest.approx(0.99)
    for _ in range(100):  # quarter turn in place
        odo.update(w @ np.array([0.0, 0.0, math.pi / 200]), np.zeros(4), 1.0)
    for _ in range(100):  # 1 m "forward" in the base frame = +y in the odometry frame
        odo.update(w @ np.array([0.01, 0.0, 0.0]), np.zeros(4), 2.0)
    o = odo.odometry()
    assert (o.x, o.y, o.yaw) == pytest.approx((1.0, 1.0, math.pi / 2), abs=1e-9)


def test_odometry_of_a_circle_closes() -> None:
    """Constant twist (v, 0, w) for one full turn: back at the start."""
    odo = OdometryIntegrator(GEOM)
    w = wheel_matrix(GEOM)
    n = 2000
    dt = 2 * math.pi / 0.5 / n
    for _ in range(n):
        odo.update(w @ (np.array([0.4, 0.0, 0.5]) * dt), np.zeros(4), 0.0)
    o = odo.odometry()
    assert math.hypot(o.x, o.y) < 1e-5
    assert o.yaw == pytest.approx(2 * math.pi)


@settings(deadline=None)
@given(st.integers(-(2**31), 2**31 - 1), st.integers(-(2**30), 2**30))
def test_wrap_delta_undoes_int32_wrap(old: int, delta: int) -> None:
    new = (old + delta + 2**31) % 2**32 - 2**31
    assert wrap_delta(new, old) == delta
