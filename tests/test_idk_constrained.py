"""Constrained min-energy: the box QP and the strategy built on it."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.optimize import minimize

from mmctl.config import default_config
from mmctl.control.idk import min_energy_block
from mmctl.control.limits import Limits
from mmctl.control.qp import box_qp
from mmctl.control.strategies import ConstrainedMinEnergy, MinEnergy, Problem
from mmctl.model import RobotModel

CFG = default_config()
MODEL = RobotModel(CFG.robot)
LIM = Limits(CFG.limits, CFG.base.mecanum)
QP = ConstrainedMinEnergy(CFG, LIM)
ME = MinEnergy(CFG)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_box_qp_is_optimal(seed) -> None:
    rng = np.random.default_rng(seed)
    n = 9
    a = rng.normal(size=(n, n))
    H = a @ a.T + 0.01 * np.eye(n)
    g = 3 * rng.normal(size=n)
    lb, ub = -rng.uniform(0, 1, n), rng.uniform(0, 1, n)
    lb[0] = ub[0] = 0.3  # an equality bound
    res = box_qp(H, g, lb, ub)
    assert res.converged
    assert np.all(res.x >= lb) and np.all(res.x <= ub)
    # KKT: the gradient pushes against every active bound, vanishes on free variables
    grad = H @ res.x + g
    free = (res.x > lb + 1e-12) & (res.x < ub - 1e-12)
    assert np.abs(grad[free]).max(initial=0.0) < 1e-8 * (1 + np.abs(g).max())
    assert np.all(grad[(res.x <= lb) & ~(lb == ub)] >= -1e-8)
    assert np.all(grad[(res.x >= ub) & ~(lb == ub)] <= 1e-8)


def _reduced_lam_min(M, J, x, lb, ub) -> float:
    """Smallest eigenvalue of J_F M_FF^-1 J_F^T on the coordinates not at a bound."""
    free = (x > lb + 1e-9) & (x < ub - 1e-9)
    Jf = J[:, free]
    return float(np.linalg.eigvalsh(Jf @ np.linalg.solve(M[np.ix_(free, free)], Jf.T))[0])


def _slsqp(M, J, v, lb, ub, x0):
    """The equality-constrained energy QP by SciPy's SLSQP (an independent solver)."""
    return minimize(
        lambda y: 0.5 * y @ M @ y, np.clip(x0, lb, ub), jac=lambda y: M @ y,
        bounds=list(zip(lb, ub)), method="SLSQP",
        constraints=[{"type": "eq", "fun": lambda y: J @ y - v, "jac": lambda y: J}],
        options={"ftol": 1e-14, "maxiter": 500},
    )


def _problem(q, v, prev=None, dt=1.0, z=None):
    return Problem(MODEL.update(q), v, q, np.zeros(9) if prev is None else prev, dt,
                   np.zeros(9) if z is None else z)


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_equals_min_energy_when_no_bound_is_active(seed) -> None:
    rng = np.random.default_rng(seed)
    q = np.concatenate((MODEL.q_des[:6] + rng.uniform(-0.3, 0.3, 6), rng.normal(size=3)))
    v = np.concatenate((0.1 * rng.normal(size=3), np.zeros(3)))
    z = 0.1 * rng.normal(size=9)
    p = _problem(q, v, z=z)
    ref = ME.solve(p)
    lb, ub = QP.bounds(p)
    assert np.all(ref > lb) and np.all(ref < ub)  # the case under test
    assert np.array_equal(QP.solve(p), ref)
    assert QP.last_iterations == 0


def test_respects_bounds_and_matches_an_independent_solver() -> None:
    """A blocked joint (at its limit) is compensated by the others: the twist is kept."""
    q = np.concatenate((MODEL.q_des[:6], [0.0, 0.0, 0.0]))
    rng = np.random.default_rng(7)
    checked = 0
    for _ in range(40):
        v = np.concatenate((0.15 * rng.normal(size=3), np.zeros(3)))
        free = min_energy_block(MODEL.update(q).J, MODEL.update(q).M_a, MODEL.M_b, v).x
        j = int(np.argmax(np.abs(free[:6])))
        qj = q.copy()
        qj[j] = (CFG.limits.joint_position_max[j] if free[j] > 0
                 else CFG.limits.joint_position_min[j])
        p = _problem(qj, v)
        x = QP.solve(p)
        lb, ub = QP.bounds(p)
        assert np.all(x >= lb - 1e-12) and np.all(x <= ub + 1e-12)
        assert abs(x[j]) < 1e-12 or np.sign(x[j]) != np.sign(free[j])
        k = p.kin
        M = MODEL.block_inertia(qj[:6])
        ref = _slsqp(M, k.J, v, lb, ub, x)
        if not ref.success or _reduced_lam_min(M, k.J, ref.x, lb, ub) < CFG.idk.singular_threshold:
            continue  # infeasible, or near singular once the bounds bite: damped by design
        checked += 1
        assert np.abs(k.J @ x - v).max() < 1e-9  # exact after the polish step
        assert 0.5 * x @ M @ x == pytest.approx(0.5 * ref.x @ M @ ref.x, rel=1e-3, abs=1e-6)
        assert np.allclose(x, ref.x, atol=2e-3)
    assert checked >= 20


def test_acceleration_bounds_from_rest_hold_over_one_cycle() -> None:
    q = MODEL.q_des.copy()
    v = np.array([0.3, 0.1, 0.0, 0.0, 0.0, 0.0])
    p = _problem(q, v, dt=0.002)
    x = QP.solve(p)
    lb, ub = QP.bounds(p)
    assert QP.last_iterations > 0
    assert np.all(x >= lb - 1e-12) and np.all(x <= ub + 1e-12)
    assert np.isfinite(x).all()
