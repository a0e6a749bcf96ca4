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
LIM = Limits(CFG.limits, CFG.base.mecanum)
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


def _check_velocity_bounds(x: np.ndarray, q: np.ndarray, J: np.ndarray) -> None:
    vmax = np.array(L.joint_velocity)
    assert np.all(np.abs(x[:6]) <= vmax * (1 + EPS))
    to_max = (np.array(L.joint_position_max) - q[:6]) / L.position_margin
    to_min = (q[:6] - np.array(L.joint_position_min)) / L.position_margin
    assert np.all(x[:6] <= vmax * np.clip(to_max, 0, 1) + EPS)
    assert np.all(-x[:6] <= vmax * np.clip(to_min, 0, 1) + EPS)
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
    # 10 % into the braking zone's depth the speed toward the limit is 10 % of v_max
    q[2] = L.joint_position_max[2] - L.position_margin / 10
    J = MODEL.jacobian(q)
    fast = np.zeros(9)
    fast[2] = 1.0
    assert np.isclose(LIM.apply(fast, np.zeros(9), q, J, 1.0).qdot[2], L.joint_velocity[2] / 10)


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
