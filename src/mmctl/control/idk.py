"""Inverse differential kinematics: the closed-form solvers (pure numpy/LAPACK).

Two plain functions for direct use, both returning the joint-velocity vector
``qdot`` (n,) for a task Jacobian ``J`` (6, n) and a desired twist ``v_d`` (6,):

* :func:`min_energy` -- the paper's minimum-kinetic-energy solution (Optimization
  Problem 1): ``qdot = J_M# v_d + (I - J_M# J) qdot_null`` with the dynamically
  consistent pseudoinverse ``J_M# = M^-1 J^T (J M^-1 J^T)^-1``;
* :func:`weighted_dls` -- the locomotion benchmark (paper eq. 7):
  ``qdot = (J^T W_a J + W_b)^-1 J^T W_a v_d + (I - J# J) qdot_null``, ``J#`` the
  Moore-Penrose pseudoinverse.

Everything is solved with Cholesky factorisations (LAPACK ``potrf/potrs/posv``),
never with explicit inverses.  Near singular task matrices (``J M^-1 J^T`` or
``J J^T``) are damped: with ``lam_min`` its smallest eigenvalue, below
``singular_threshold`` the matrix gets ``delta I`` added, where
``delta = max_damping * (1 - (lam_min / singular_threshold)^2)`` (0 at the threshold,
``max_damping`` at an exactly singular matrix; Nakamura/Chiaverini style), so the
result stays finite and continuous.  ``J M^-1 J^T`` is the inverse of the operational
space inertia: its eigenvalues are inverse effective masses [1/kg] (1e-3 is an
effective mass of 1000 kg in the heaviest direction).

:func:`min_energy_block` is the same solution exploiting ``M = blockdiag(M_a, M_b)``
with diagonal ``M_b`` (only the 6x6 ``M_a`` is factorised); the controller uses it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

Vec = NDArray[np.float64]

_potrf = lapack.dpotrf
_potrs = lapack.dpotrs
_posv = lapack.dposv
_syev = lapack.dsyev
_trtri = lapack.dtrtri

#: Defaults equal to the ``idk:`` config defaults.
SINGULAR_THRESHOLD = 1e-3
MAX_DAMPING = 1e-2


class TaskSolve(NamedTuple):
    """A damped task-space solve: ``x`` and bounds on the task matrix's eigenvalues.

    When no damping was needed, ``lam_min`` is the lower bound ``1 / trace(A^-1)``
    and ``lam_max`` the upper bound ``trace(A)`` (cheap, from the Cholesky factor);
    otherwise both are the exact extreme eigenvalues.
    """

    x: Vec
    lam_min: float
    lam_max: float
    damping: float


def damping_for(lam_min: float, threshold: float, max_damping: float) -> float:
    """The damping ``delta`` added to a task matrix whose smallest eigenvalue is ``lam_min``."""
    if lam_min >= threshold:
        return 0.0
    r = max(lam_min, 0.0) / threshold
    return max_damping * (1.0 - r * r)


def solve_spd(a: Vec, b: Vec) -> Vec:
    """Solve ``a x = b`` for symmetric positive definite ``a`` (Cholesky).

    Falls back to least squares (SVD) when ``a`` is not numerically positive definite.
    """
    _, x, info = _posv(a, b, lower=1)
    if info != 0:
        x = np.linalg.lstsq(a, b, rcond=None)[0]
    sol: Vec = x
    return sol


def damped_task_solve(
    a: Vec, r: Vec, threshold: float = SINGULAR_THRESHOLD, max_damping: float = MAX_DAMPING
) -> TaskSolve:
    """Solve ``(a + delta I) x = r`` for a PSD task matrix ``a`` (6, 6), damped as documented.

    Fast path: Cholesky of ``a`` and the bound ``lam_min >= 1 / trace(a^-1)`` (from the
    inverse factor); only when that bound is below ``threshold`` are the eigenvalues
    computed (LAPACK ``syev``) to set the damping.
    """
    L, info = _potrf(a, lower=1, clean=1)
    if info == 0:
        Li, info = _trtri(L, lower=1)
        f = Li.ravel(order="K")  # no copy (LAPACK returns Fortran order)
        tr_inv = float(f @ f)  # trace(a^-1) = |L^-1|_F^2
        if info == 0 and tr_inv * threshold <= 1.0:
            x, _ = _potrs(L, r, lower=1)
            return TaskSolve(x, 1.0 / tr_inv, float(a.trace()), 0.0)
    w, _, info = _syev(a, compute_v=0)
    if info != 0 or not np.isfinite(w[0]):
        return TaskSolve(np.full(r.shape, np.nan), float("nan"), float("nan"), 0.0)
    lam_min, lam_max = float(w[0]), float(w[-1])
    delta = damping_for(lam_min, threshold, max_damping)
    if delta > 0.0:
        a = a + delta * np.eye(a.shape[0])
    return TaskSolve(solve_spd(a, r), lam_min, lam_max, delta)


def _as_vec(v: Vec) -> Vec:
    return np.asarray(v, dtype=float).reshape(-1)


def min_energy(
    J: Vec,
    M: Vec,
    v_d: Vec,
    qdot_null: Vec | None = None,
    *,
    singular_threshold: float = SINGULAR_THRESHOLD,
    max_damping: float = MAX_DAMPING,
) -> Vec:
    """Minimum-kinetic-energy joint velocities (n,) with ``J qdot = v_d``.

    J: (6, n) task Jacobian; M: (n, n) symmetric positive definite inertia
    (``E_K = qdot^T M qdot / 2``); v_d: (6,) desired twist; qdot_null: (n,) secondary
    velocity, projected with the dynamically consistent projector ``I - J_M# J``
    (i.e. the result is the ``M``-closest solution to ``qdot_null``).
    Raises ValueError if ``M`` is not positive definite.
    """
    J = np.asarray(J, dtype=float)
    L, info = _potrf(np.asarray(M, dtype=float), lower=1, clean=1)
    if info != 0:
        raise ValueError("M must be symmetric positive definite")
    Y, _ = _potrs(L, J.T, lower=1)  # M^-1 J^T
    r = _as_vec(v_d)
    if qdot_null is not None:
        qdot_null = _as_vec(qdot_null)
        r = r - J @ qdot_null
    lam = damped_task_solve(J @ Y, r, singular_threshold, max_damping).x
    out: Vec = Y @ lam
    return out if qdot_null is None else out + qdot_null


def min_energy_block(
    J: Vec,
    M_a: Vec,
    m_b: Vec,
    v_d: Vec,
    qdot_null: Vec | None = None,
    singular_threshold: float = SINGULAR_THRESHOLD,
    max_damping: float = MAX_DAMPING,
) -> TaskSolve:
    """:func:`min_energy` for ``M = blockdiag(M_a (6, 6), diag(m_b) (3,))``, J (6, 9).

    Only the 6x6 ``M_a`` is factorised; ``J_b`` must have the planar-base structure
    of :func:`mmctl.model.robot.base_jacobian` (columns e_x, e_y and
    ``(-p_y, p_x, 0, 0, 0, 1)``), whose term ``J_b M_b^-1 J_b^T`` is written out.
    Returns the (9,) solution as ``x`` plus the eigenvalue range of ``J M^-1 J^T``.
    """
    L, info = _potrf(M_a, lower=1, clean=0)
    if info != 0:
        return TaskSolve(np.full(9, np.nan), float("nan"), float("nan"), 0.0)
    Ja = J[:, :6]
    Ya, _ = _potrs(L, Ja.T, lower=1)  # M_a^-1 J_a^T (6, 6)
    A = Ja @ Ya
    mx, my, i_z = m_b.tolist()
    px, py = float(J[1, 8]), -float(J[0, 8])
    imx, imy, iz = 1.0 / mx, 1.0 / my, 1.0 / i_z
    a01 = -py * px * iz
    a05, a15 = -py * iz, px * iz
    A[0, 0] += imx + py * py * iz
    A[1, 1] += imy + px * px * iz
    A[5, 5] += iz
    A[0, 1] += a01
    A[1, 0] += a01
    A[0, 5] += a05
    A[5, 0] += a05
    A[1, 5] += a15
    A[5, 1] += a15
    r = v_d if qdot_null is None else v_d - J @ qdot_null
    sol = damped_task_solve(A, r, singular_threshold, max_damping)
    lam = sol.x
    x = np.empty(9)
    x[:6] = Ya @ lam
    l0, l1, _, _, _, l5 = lam.tolist()
    x[6] = l0 * imx
    x[7] = l1 * imy
    x[8] = (-py * l0 + px * l1 + l5) * iz
    if qdot_null is not None:
        x += qdot_null
    return sol._replace(x=x)


def _weights(w: Vec, n: int, name: str) -> Vec:
    w = np.asarray(w, dtype=float)
    if w.ndim == 1 and w.shape == (n,):
        return w
    if w.shape == (n, n):
        return w
    raise ValueError(f"{name} must be ({n},) or ({n}, {n}), got {w.shape}")


def null_project(
    J: Vec, z: Vec, threshold: float = SINGULAR_THRESHOLD, max_damping: float = MAX_DAMPING
) -> TaskSolve:
    """``(I - J# J) z`` with the (damped) Moore-Penrose pseudoinverse ``J# = J^T (J J^T)^-1``.

    ``x`` is the projected vector; the eigenvalues are those of ``J J^T``.
    """
    sol = damped_task_solve(J @ J.T, J @ z, threshold, max_damping)
    return sol._replace(x=z - J.T @ sol.x)


def weighted_dls(
    J: Vec,
    v_d: Vec,
    W_alpha: Vec,
    W_beta: Vec,
    qdot_null: Vec | None = None,
    *,
    singular_threshold: float = SINGULAR_THRESHOLD,
    max_damping: float = MAX_DAMPING,
) -> Vec:
    """Damped weighted least squares (paper eq. 7), (n,) joint velocities.

    Minimises ``|v_d - J qdot|^2_{W_alpha} / 2 + |qdot|^2_{W_beta}`` as written in the
    paper's closed form ``(J^T W_a J + W_b)^-1 J^T W_a v_d``; W_alpha (6,) or (6, 6),
    W_beta (n,) or (n, n) (diagonals or full matrices, positive semi-definite with
    ``J^T W_a J + W_b`` positive definite); qdot_null: (n,) secondary velocity,
    projected with ``I - J# J``.
    """
    J = np.asarray(J, dtype=float)
    n = J.shape[1]
    wa = _weights(W_alpha, 6, "W_alpha")
    wb = _weights(W_beta, n, "W_beta")
    jtw = J.T * wa if wa.ndim == 1 else J.T @ wa
    h = jtw @ J
    if wb.ndim == 1:
        h[np.diag_indices(n)] += wb
    else:
        h = h + wb
    out = solve_spd(h, jtw @ _as_vec(v_d))
    if qdot_null is not None:
        out = out + null_project(J, _as_vec(qdot_null), singular_threshold, max_damping).x
    return out
