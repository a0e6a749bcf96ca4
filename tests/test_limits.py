"""Limits: never exceed a bound, keep the direction of qdot, brake at position limits."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from mmctl.config import default_config
from mmctl.control.limits import Limits
from mmctl.control.mecanum import wheel_matrix
from mmctl.model import RobotModel

CFG = default_config()
LIM = Limits(CFG.limits, CFG.base.mecanum, CFG.arm.speedj_acceleration)
MODEL = RobotModel(CFG.robot)
L = CFG.limits
W = wheel_matrix(CFG.base.mecanum)
T = 0.002
EPS = 1e-9

vec9 = st.lists(st.floats(-20.0, 20.0), min_size=9, max_size=9)


def _q(rng: np.random.Generator, near_limit: bool) -> np.ndarray:
    qa = rng.uniform(-3.0, 3.0, 6)
    if near_limit:  # put a few joints inside the braking zone or beyond the limit
        j = rng.integers(0, 6, 2)
        qa[j] = np.array(L.joint_position_max)[j] - rng.uniform(-0.05, 0.2, 2)
    return np.concatenate((qa, rng.uniform(-2, 2, 3)))


def braking_cap(distance_to_rest: np.ndarray) -> np.ndarray:
    """Speed [rad/s] a joint may have toward its limit: it can still stop (on 80 % of
    the acceleration limit) by the point ``position_margin`` inside the limit."""
    a_b = 0.8 * np.minimum(np.array(L.joint_acceleration), CFG.arm.speedj_acceleration)
    v = np.sqrt(2 * a_b * np.clip(distance_to_rest, 0, None))
    return np.minimum(np.array(L.joint_velocity), v)


def _check_velocity_bounds(x: np.ndarray, q: np.ndarray, J: np.ndarray) -> None:
    vmax = np.array(L.joint_velocity)
    assert np.all(np.abs(x[:6]) <= vmax * (1 + EPS))
    to_max = np.array(L.joint_position_max) - L.position_margin - q[:6]
    to_min = q[:6] - np.array(L.joint_position_min) - L.position_margin
    assert np.all(x[:6] <= braking_cap(to_max) + EPS)
    assert np.all(-x[:6] <= braking_cap(to_min) + EPS)
    assert math.hypot(x[6], x[7]) <= L.base_linear_velocity * (1 + EPS)
    assert abs(x[8]) <= L.base_angular_velocity * (1 + EPS)
    assert np.abs(W @ x[6:]).max() <= L.wheel_velocity * (1 + EPS)
    v = J @ x
    assert np.linalg.norm(v[:3]) <= L.ee_linear_velocity * (1 + EPS)
    assert np.linalg.norm(v[3:]) <= L.ee_angular_velocity * (1 + EPS)


def _check_acceleration(x: np.ndarray, prev: np.ndarray) -> None:
    d = x - prev
    assert np.all(np.abs(d[:6]) <= np.array(L.joint_acceleration) * T * (1 + EPS))
    assert math.hypot(d[6], d[7]) <= L.base_linear_acceleration * T * (1 + EPS)
    assert abs(d[8]) <= L.base_angular_acceleration * T * (1 + EPS)


@settings(max_examples=300, deadline=None)
@given(vec9, st.integers(0, 2**32 - 1), st.booleans())
def test_from_rest_every_bound_holds_and_direction_is_kept(qd, seed, near_limit) -> None:
    rng = np.random.default_rng(seed)
    q = _q(rng, near_limit)
    J = MODEL.jacobian(q)
    qd = np.array(qd)
    res = LIM.apply(qd, np.zeros(9), q, J, T)
    x = res.qdot
    _check_velocity_bounds(x, q, J)
    _check_acceleration(x, np.zeros(9))
    # direction kept: x = s qd with s in [0, 1]
    s = res.scale * res.accel_scale * res.final_scale
    assert 0.0 <= s <= 1.0
    assert np.allclose(x, s * qd, atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(vec9, vec9, st.integers(0, 2**32 - 1))
def test_from_motion_the_change_keeps_its_direction(qd, prev, seed) -> None:
    rng = np.random.default_rng(seed)
    q = _q(rng, False)
    J = MODEL.jacobian(q)
    # a previous command that met the limits
    prev = LIM.apply(np.array(prev), np.zeros(9), q, J, 1.0).qdot
    res = LIM.apply(np.array(qd), prev, q, J, T)
    _check_velocity_bounds(res.qdot, q, J)
    _check_acceleration(res.qdot, prev)
    target = res.scale * np.array(qd)
    assert np.allclose(res.qdot, prev + res.accel_scale * (target - prev), atol=1e-12)


def test_no_motion_toward_a_joint_beyond_its_limit_but_away_is_free() -> None:
    q = MODEL.q_des.copy()
    q[2] = L.joint_position_max[2] + 0.01  # elbow past its upper limit
    J = MODEL.jacobian(q)
    toward = np.zeros(9)
    toward[2], toward[6] = 0.5, 0.3
    assert np.all(LIM.apply(toward, np.zeros(9), q, J, 1.0).qdot == 0.0)
    away = np.zeros(9)
    away[2] = -0.5
    assert np.allclose(LIM.apply(away, np.zeros(9), q, J, 1.0).qdot, away)
    # inside the margin: at rest toward the limit
    q[2] = L.joint_position_max[2] - L.position_margin / 2
    J = MODEL.jacobian(q)
    fast = np.zeros(9)
    fast[2] = 1.0
    assert LIM.apply(fast, np.zeros(9), q, J, 1.0).qdot[2] == 0.0
    # 0.05 rad before the rest point: sqrt(2 * 0.8 * 4 rad/s^2 * 0.05 rad) = 0.566 rad/s
    q[2] = L.joint_position_max[2] - L.position_margin - 0.05
    J = MODEL.jacobian(q)
    assert np.isclose(LIM.apply(fast, np.zeros(9), q, J, 1.0).qdot[2], math.sqrt(0.32))


def test_a_joint_driven_at_its_limit_comes_to_rest_inside_the_margin() -> None:
    """The soak's protective stops: wrist 3 pushed toward -2 pi at full speed (3.1 rad/s)
    overshot a linear 0.15 rad braking zone by ~1 rad (the arm follows speedJ at 4
    rad/s^2) into the controller's joint limit.  Here the limited command drives the
    simulated robot's joints (the plant the fake UR runs, at the speedJ acceleration)
    toward each limit of each joint, from full speed: every joint stops inside its
    limit, within the margin, and no closer to the limit than the margin allows."""
    from mmctl.sim.joints import JointPlant

    for j in range(6):
        for sign in (1.0, -1.0):
            q = np.concatenate((MODEL.q_des[:6], np.zeros(3)))
            limit = L.joint_position_max[j] if sign > 0 else L.joint_position_min[j]
            q[j] = limit - sign * 3.0  # 3 rad away: room to reach full speed and brake
            plant = JointPlant(list(q[:6]), q_min=L.joint_position_min[j] - 1.0,
                               q_max=L.joint_position_max[j] + 1.0)
            want = np.zeros(9)
            want[j] = sign * 10.0  # far above any speed limit
            prev = np.zeros(9)
            peak = 0.0
            for _ in range(3000):  # 6 s
                q[:6] = plant.q
                x = LIM.apply(want, prev, q, MODEL.jacobian(q), T).qdot
                prev = x
                plant.speed(list(x[:6]), CFG.arm.speedj_acceleration)
                plant.step(T)
                peak = max(peak, abs(plant.qd[j]))
            # fast: the end-effector speed cap may bind first (joint 1 turns the whole arm)
            assert peak > 1.0, (j, sign, peak)
            stop = plant.q[j]
            assert abs(plant.qd[j]) < 1e-9, (j, sign)  # at rest
            inside = sign * (limit - stop)  # how far inside the limit it stopped
            assert L.position_margin * 0.9 <= inside <= L.position_margin + 0.01, (j, sign, inside)


def test_non_finite_gives_zero() -> None:
    q = MODEL.q_des
    bad = np.full(9, np.nan)
    assert np.all(LIM.apply(bad, np.zeros(9), q, MODEL.jacobian(q), T).qdot == 0.0)


def test_box_bounds_contain_rest_and_respect_acceleration() -> None:
    q = MODEL.q_des
    prev = np.full(9, 0.1)
    lb, ub = LIM.box_bounds(q, prev, T)
    assert np.all(lb <= ub)
    assert np.all(ub - prev <= np.r_[np.array(L.joint_acceleration) * T,
                                     [L.base_linear_acceleration * T] * 2,
                                     L.base_angular_acceleration * T] + 1e-15)
    # a previous command outside the speed box: the bound is the nearest admissible point
    prev[0] = 10.0
    lb, ub = LIM.box_bounds(q, prev, T)
    assert lb[0] == ub[0] == L.joint_velocity[0]
