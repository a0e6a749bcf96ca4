"""The simulated robot's one plant (`mmctl.sim.plant`): the fake UR's joints and the fake
drives' wheels, commanded as the daemon commands them, in simulated time.

These tests run the ideal base (no latency, velocity loop or slip: ``IDEAL``); the base's
dynamics are tested in ``test_base_dynamics.py``."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mmctl.config import config_from_dict
from mmctl.control.mecanum import twist_to_wheels
from mmctl.sim.plant import Plant

DT = 0.002
IDEAL = {"base_latency": 0.0, "base_velocity_tau": 0.0, "base_slip_longitudinal": 0.0,
         "base_slip_lateral": 0.0}
CFG = config_from_dict({"sim": IDEAL})
ARM_ACC = CFG.arm.speedj_acceleration
WHEEL_ACC = CFG.limits.base_linear_acceleration / CFG.base.mecanum.wheel_radius
finite = st.floats(-2.0, 2.0, allow_nan=False)


def rest(q: list[float] | None = None) -> Plant:
    return Plant(CFG, np.zeros(9) if q is None else q)


@settings(max_examples=40, deadline=None)
@given(st.lists(finite, min_size=6, max_size=6), st.lists(finite, min_size=3, max_size=3))
def test_every_step_keeps_the_devices_acceleration_limits(arm: list[float],
                                                          twist: list[float]) -> None:
    """speedJ: the leading joint at arm.speedj_acceleration, the others scaled with it
    (the change keeps its direction); each wheel at its drive's acceleration."""
    plant = rest()
    before = plant.state()
    w_before = plant.wheels.omega.copy()
    for _ in range(3):
        after = plant.step(arm, twist, DT)
        dq = after.qd[:6] - before.qd[:6]
        assert np.abs(dq).max() <= ARM_ACC * DT + 1e-12
        want = np.asarray(arm) - before.qd[:6]
        if np.abs(want).max() > ARM_ACC * DT:  # limited: parallel to what was asked
            np.testing.assert_allclose(dq * np.abs(want).max(), want * np.abs(dq).max(),
                                       atol=1e-12)
        assert np.abs(plant.wheels.omega - w_before).max() <= WHEEL_ACC * DT + 1e-9
        before, w_before = after, plant.wheels.omega.copy()


def test_the_base_reaches_its_twist_at_the_wheel_acceleration() -> None:
    plant = rest()
    twist = np.array([0.3, -0.2, 0.1])
    wheels = twist_to_wheels(CFG.base.mecanum, twist)
    ramp = float(np.abs(wheels).max()) / WHEEL_ACC  # [s] the leading wheel's ramp
    s = plant.step(np.zeros(6), twist, DT)
    steps = math.ceil(ramp / DT) + 2
    for _ in range(steps):
        s = plant.step(np.zeros(6), twist, DT)
    np.testing.assert_allclose(plant.wheels.omega, wheels, atol=1e-9)
    np.testing.assert_allclose(s.qd[6:], twist, atol=1e-9)  # the odometry's twist


def test_a_twist_beyond_the_wheel_limit_is_scaled_as_the_transport_scales_it() -> None:
    plant = rest()
    twist = np.array([5.0, 5.0, 0.0])  # far beyond limits.wheel_velocity
    for _ in range(2000):
        s = plant.step(np.zeros(6), twist, DT)
    assert np.abs(plant.wheels.omega).max() == pytest.approx(CFG.limits.wheel_velocity)
    assert s.qd[6] == pytest.approx(s.qd[7])  # direction kept
    assert s.qd[6] < 5.0


def test_the_arm_converges_and_positions_integrate() -> None:
    plant = rest([0.1, 0, 0, 0, 0, 0, 1.0, 2.0, math.pi / 2])
    for _ in range(2000):
        s = plant.step(np.full(6, 0.2), [0.5, 0.0, 0.0], DT)
    np.testing.assert_allclose(s.qd, [0.2] * 6 + [0.5, 0.0, 0.0], atol=1e-9)
    # base heading +y in the world: forward speed moves y, not x
    assert s.q[6] == pytest.approx(1.0, abs=1e-9)
    assert s.q[7] > 2.0 + 0.5 * 3.0
    assert s.q[8] == pytest.approx(math.pi / 2)
    assert s.q[0] > 0.1 + 0.2 * 3.0


def test_a_rotating_base_drives_a_circle() -> None:
    plant = rest()
    v, w = 0.2, 0.2
    for _ in range(200):  # up to speed (the ramp: well under 0.4 s)
        plant.step(np.zeros(6), [v, 0.0, w], DT)
    s = plant.state()
    start = s.q[6:8].copy()
    n = round(2 * math.pi / w / DT)  # one full circle of radius v / w
    for _ in range(n):
        s = plant.step(np.zeros(6), [v, 0.0, w], DT)
    assert math.hypot(*(s.q[6:8] - start)) < 2e-3


def test_validation() -> None:
    with pytest.raises(ValueError, match="shape"):
        Plant(CFG, np.zeros(6))
    with pytest.raises(ValueError, match="dt"):
        rest().step(np.zeros(6), np.zeros(3), 0.0)
