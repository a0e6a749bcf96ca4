"""Min-energy and weighted-DLS inverse differential kinematics: properties on the model."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from mmctl.config import default_config
from mmctl.control.energy import kinetic_energy
from mmctl.control.idk import (
    damping_for,
    min_energy,
    min_energy_block,
    null_project,
    weighted_dls,
)
from mmctl.model import RobotModel

CFG = default_config()
MODEL = RobotModel(CFG.robot)
THR = CFG.idk.singular_threshold

angles = st.lists(st.floats(-math.pi, math.pi), min_size=6, max_size=6)
twists = st.lists(st.floats(-1.0, 1.0), min_size=6, max_size=6)
seeds = st.integers(0, 2**32 - 1)


def _kin(qa: list[float], base: tuple[float, float, float] = (0.3, -0.2, 0.7)):
    q = np.array(list(qa) + list(base))
    return q, MODEL.update(q)


def _null_basis(J: np.ndarray) -> np.ndarray:
    _, _, vt = np.linalg.svd(J)
    return vt[6:].T  # (9, 3)


@settings(max_examples=300, deadline=None)
@given(angles, twists, seeds)
def test_min_energy_tracks_the_twist_and_is_the_kkt_solution(qa, v, seed) -> None:
    q, k = _kin(qa)
    v = np.array(v)
    sol = min_energy_block(k.J, k.M_a, k.M_b, v)
    assume(sol.lam_min > THR)  # undamped regime: the exact solution
    x = sol.x
    assert np.abs(k.J @ x - v).max() < 1e-9
    M = MODEL.block_inertia(q[:6])
    # the general function (full Cholesky of M) agrees with the block one
    assert np.allclose(min_energy(k.J, M, v), x, atol=1e-9, rtol=1e-9)
    # the KKT system  [M J^T; J 0] [x; lam] = [0; v]  solved directly
    kkt = np.block([[M, k.J.T], [k.J, np.zeros((6, 6))]])
    ref = np.linalg.solve(kkt, np.concatenate((np.zeros(9), v)))[:9]
    assert np.allclose(x, ref, atol=1e-8 * (1 + np.abs(ref).max()))
    # any null-space motion costs energy
    n = _null_basis(k.J) @ np.random.default_rng(seed).normal(size=3)
    e0 = kinetic_energy(k.M_a, k.M_b, x).total
    for scale in (1e-3, 0.1, 1.0):
        assert e0 <= kinetic_energy(k.M_a, k.M_b, x + scale * n).total + 1e-12


@settings(max_examples=200, deadline=None)
@given(angles, twists)
def test_identity_metric_gives_the_moore_penrose_solution(qa, v) -> None:
    _, k = _kin(qa)
    s = np.linalg.svd(k.J, compute_uv=False)
    assume(s[-1] ** 2 > THR)
    v = np.array(v)
    x = min_energy(k.J, np.eye(9), v)
    assert np.allclose(x, np.linalg.pinv(k.J) @ v, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(angles, twists, st.lists(st.floats(-2.0, 2.0), min_size=9, max_size=9))
def test_null_space_term_does_not_change_the_end_effector_twist(qa, v, z) -> None:
    _, k = _kin(qa)
    v, z = np.array(v), np.array(z)
    plain = min_energy_block(k.J, k.M_a, k.M_b, v)
    assume(plain.lam_min > THR)
    with_null = min_energy_block(k.J, k.M_a, k.M_b, v, z).x
    assert np.abs(k.J @ with_null - k.J @ plain.x).max() < 1e-9
    # and it is the M-closest task solution to z: (x - z) is M-orthogonal to null(J)
    M = MODEL.block_inertia(np.array(qa))
    assert np.abs(_null_basis(k.J).T @ M @ (with_null - z)).max() < 1e-8
    # the plain function's qdot_null is the same thing
    assert np.allclose(min_energy(k.J, M, v, z), with_null, atol=1e-9)


def test_singular_task_matrix_is_damped_not_nan() -> None:
    rng = np.random.default_rng(0)
    J = rng.normal(size=(6, 9))
    J[5] = J[4]  # rank 5
    M = np.diag(rng.uniform(0.5, 2.0, 9))
    v = rng.normal(size=6)
    x = min_energy(J, M, v)
    assert np.isfinite(x).all()
    x2 = weighted_dls(J, v, np.ones(6), np.zeros(9), rng.normal(size=9))
    assert np.isfinite(x2).all()
    assert np.isfinite(null_project(np.zeros((6, 9)), np.ones(9)).x).all()
    # damping is continuous: 0 at the threshold, max at zero
    assert damping_for(THR, THR, 0.01) == 0.0
    assert damping_for(0.0, THR, 0.01) == 0.01
    assert damping_for(-1.0, THR, 0.01) == 0.01
    with pytest.raises(ValueError, match="positive definite"):
        min_energy(J, -np.eye(9), v)


def _reachable_cases(n: int, seed: int, horizontal: bool = False):
    """Configurations near q_des and 0.2 m/s end-effector motions, orientation fixed."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        q = np.concatenate((MODEL.q_des[:6] + rng.uniform(-0.4, 0.4, 6), [0.0, 0.0, 0.0]))
        d = rng.normal(size=3)
        if horizontal:
            d[2] = 0.0
        v = np.concatenate((0.2 * d / np.linalg.norm(d), np.zeros(3)))
        yield q, MODEL.update(q), v


def test_min_energy_base_share_is_small_with_the_paper_base_mass() -> None:
    """m_b = 115 kg: the base gets ~10 % of E_K (median; measured 9.9 %, p90 16 %)."""
    shares = [
        kinetic_energy(k.M_a, k.M_b, min_energy_block(k.J, k.M_a, k.M_b, v).x).base_share()
        for _, k, v in _reachable_cases(500, 1)
    ]
    assert np.median(shares) < 0.15
    assert np.percentile(shares, 90) < 0.25


def test_weighted_dls_matches_the_closed_form_and_accepts_matrices() -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        J = rng.normal(size=(6, 9))
        v, z = rng.normal(size=6), rng.normal(size=9)
        wa, wb = rng.uniform(0.5, 2.0, 6), rng.uniform(0.01, 1.0, 9)
        ref = np.linalg.inv(J.T @ np.diag(wa) @ J + np.diag(wb)) @ J.T @ np.diag(wa) @ v
        ref += (np.eye(9) - np.linalg.pinv(J) @ J) @ z
        assert np.allclose(weighted_dls(J, v, wa, wb, z), ref, atol=1e-9)
        assert np.allclose(weighted_dls(J, v, np.diag(wa), np.diag(wb), z), ref, atol=1e-9)
    with pytest.raises(ValueError, match="W_beta"):
        weighted_dls(J, v, wa, np.ones(5))


def test_locomotion_defaults_make_the_base_carry_the_motion() -> None:
    """Horizontal pushes near q_des: the base makes >= 95 % of the end-effector velocity
    (measured median 99.99 %, arm joint speeds ~1e-4 rad/s) and the arm stays put."""
    wa = np.array(CFG.idk.locomotion.w_alpha)
    wb = np.array(CFG.idk.locomotion.w_beta)
    shares, arm_speed, errors = [], [], []
    for _, k, v in _reachable_cases(300, 3, horizontal=True):
        x = weighted_dls(k.J, v, wa, wb)
        shares.append(np.linalg.norm(k.J[:3, 6:] @ x[6:]) / np.linalg.norm(v[:3]))
        arm_speed.append(np.abs(x[:6]).max())
        errors.append(np.abs(k.J @ x - v).max())
    assert np.median(shares) > 0.95
    assert np.median(arm_speed) < 0.05
    assert max(errors) < 0.01 * 0.2  # the damping costs < 1 % of the twist
