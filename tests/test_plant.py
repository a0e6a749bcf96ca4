"""Simulated plant: acceleration limits, first-order lag, pose integration."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mmctl.config import default_config
from mmctl.sim.plant import Plant, PlantParams, initial_state

DT = 0.002
finite = st.floats(-5.0, 5.0, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(st.lists(finite, min_size=9, max_size=9), st.lists(finite, min_size=9, max_size=9))
def test_acceleration_limits_hold(qd0: list[float], cmd: list[float]) -> None:
    p = PlantParams(arm_tau=0.0, base_tau=0.0)
    plant = Plant(p)
    s = initial_state(np.zeros(9))._replace(qd=np.array(qd0))
    for _ in range(3):
        n = plant.step(s, cmd[:6], cmd[6:], DT)
        dq = n.qd - s.qd
        assert np.all(np.abs(dq[:6]) <= np.asarray(p.arm_acceleration) * DT + 1e-12)
        assert math.hypot(dq[6], dq[7]) <= p.base_linear_acceleration * DT + 1e-12
        assert abs(dq[8]) <= p.base_angular_acceleration * DT + 1e-12
        s = n


def test_base_linear_limit_keeps_direction() -> None:
    plant = Plant(PlantParams(base_tau=0.0))
    s = plant.step(initial_state(np.zeros(9)), np.zeros(6), [3.0, 4.0, 0.0], DT)
    assert s.qd[6] / s.qd[7] == pytest.approx(0.75)
    assert math.hypot(s.qd[6], s.qd[7]) == pytest.approx(3.0 * DT)


def test_first_order_lag_below_the_acceleration_limit() -> None:
    tau = 0.05
    p = PlantParams(arm_tau=tau, arm_acceleration=(1e6,) * 6, base_tau=2 * tau,
                    base_linear_acceleration=1e6, base_angular_acceleration=1e6)
    plant = Plant(p)
    s = initial_state(np.zeros(9))
    cmd_a, cmd_b = np.full(6, 0.5), np.array([0.2, -0.1, 0.3])
    for k in range(1, 101):
        s = plant.step(s, cmd_a, cmd_b, DT)
        t = k * DT
        np.testing.assert_allclose(s.qd[:6], cmd_a * (1 - math.exp(-t / tau)), rtol=1e-9)
        np.testing.assert_allclose(s.qd[6:], cmd_b * (1 - math.exp(-t / (2 * tau))), rtol=1e-9)


def test_acceleration_limit_dominates_large_steps() -> None:
    p = PlantParams(arm_tau=0.02, arm_acceleration=(2.0,) * 6)
    plant = Plant(p)
    s = initial_state(np.zeros(9))
    for k in range(1, 51):
        s = plant.step(s, np.full(6, 1.0), np.zeros(3), DT)
        assert s.qd[0] == pytest.approx(min(2.0 * k * DT, 1.0), abs=1e-9)  # ramp at 2 rad/s^2


def test_converges_and_integrates_positions() -> None:
    plant = Plant(PlantParams())
    s = initial_state([0.1, 0, 0, 0, 0, 0, 1.0, 2.0, math.pi / 2])
    for _ in range(2000):
        s = plant.step(s, np.full(6, 0.2), [0.5, 0.0, 0.0], DT)
    np.testing.assert_allclose(s.qd, [0.2] * 6 + [0.5, 0.0, 0.0], atol=1e-9)
    # base heading +y in the world: forward speed moves y, not x
    assert s.q[6] == pytest.approx(1.0, abs=1e-9)
    assert s.q[7] > 2.0 + 0.5 * 3.0
    assert s.q[8] == pytest.approx(math.pi / 2)
    assert s.q[0] > 0.1 + 0.2 * 3.0


def test_rotating_base_integrates_on_an_arc() -> None:
    plant = Plant(PlantParams(base_tau=0.0, base_linear_acceleration=1e6,
                              base_angular_acceleration=1e6))
    s = initial_state(np.zeros(9))
    v, w = 0.5, 0.5
    n = round(2 * math.pi / w / DT)  # one full circle of radius v / w
    for _ in range(n):
        s = plant.step(s, np.zeros(6), [v, 0.0, w], DT)
    assert math.hypot(s.q[6], s.q[7]) < 1e-3


def test_from_config_and_validation() -> None:
    cfg = default_config()
    p = PlantParams.from_config(cfg)
    assert p.base_linear_acceleration == cfg.limits.base_linear_acceleration
    assert p.arm_acceleration == tuple(cfg.limits.joint_acceleration)
    with pytest.raises(ValueError):
        PlantParams(arm_tau=-1.0)
    with pytest.raises(ValueError):
        initial_state(np.zeros(6))
    with pytest.raises(ValueError):
        Plant(p).step(initial_state(np.zeros(9)), np.zeros(6), np.zeros(3), 0.0)
