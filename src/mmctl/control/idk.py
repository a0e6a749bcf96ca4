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
with diagonal ``M_b``; the controller uses it.  These run every 2 ms in Python, where
each numpy or LAPACK call costs a few thousand instructions whatever the size: the
solvers make few of them (one ``posv`` for ``M^-1 J^T``, ``ndarray.dot``, positional
arguments to the LAPACK wrappers), and the flops of a 9x9 solve do not matter.
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
    _, x, info = _posv(a, b, 1)  # lower
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
    return TaskSolve(*_damped(a, r, threshold, max_damping))


def _damped(a: Vec, r: Vec, threshold: float, max_damping: float
            ) -> tuple[Vec, float, float, float]:
    """:func:`damped_task_solve` as a plain tuple (x, lam_min, lam_max, damping)."""
    L, info = _potrf(a, 1, 1)  # lower, the upper part zeroed
    if info == 0:
        Li, info = _trtri(L, 1)
        f = Li.ravel(order="K")  # no copy (LAPACK returns Fortran order)
        tr_inv = float(f.dot(f))  # trace(a^-1) = |L^-1|_F^2
        if info == 0 and tr_inv * threshold <= 1.0:
            x, _ = _potrs(L, r, 1)
            f = L.ravel(order="K")
            return x, 1.0 / tr_inv, float(f.dot(f)), 0.0  # trace(a) = |L|_F^2
    w, _, info = _syev(a, compute_v=0)
    if info != 0 or not np.isfinite(w[0]):
        return np.full(r.shape, np.nan), float("nan"), float("nan"), 0.0
    lam_min, lam_max = float(w[0]), float(w[-1])
    delta = damping_for(lam_min, threshold, max_damping)
    if delta > 0.0:
        a = a + delta * np.eye(a.shape[0])
    return solve_spd(a, r), lam_min, lam_max, delta


def _as_vec(v: Vec) -> Vec:
    return np.asarray(v, dtype=float).reshape(-1)


def _min_energy(J: Vec, M: Vec, v_d: Vec, qdot_null: Vec | None, threshold: float,
                max_damping: float, scratch: int) -> tuple[Vec, float, float, float] | None:
    """The min-energy solve on arrays as (x, lam_min, lam_max, damping), None if ``M``
    is not positive definite: ``Y = M^-1 J^T`` in one ``posv`` (``scratch``: ``M`` is
    Fortran-ordered and may be overwritten), the task matrix ``J M^-1 J^T = J Y``, then
    ``x = Y lam + qdot_null`` with ``(J Y) lam = v_d - J qdot_null``."""
    _, Y, info = _posv(M, J.T, 1, scratch)  # lower
    if info != 0:
        return None
    r = v_d if qdot_null is None else v_d - J.dot(qdot_null)
    lam, lam_min, lam_max, delta = _damped(J.dot(Y), r, threshold, max_damping)
    x: Vec = Y.dot(lam)
    if qdot_null is not None:
        x += qdot_null
    return x, lam_min, lam_max, delta


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
    sol = _min_energy(np.asarray(J, dtype=float), np.asarray(M, dtype=float), _as_vec(v_d),
                      None if qdot_null is None else _as_vec(qdot_null), singular_threshold,
                      max_damping, 0)
    if sol is None:
        raise ValueError("M must be symmetric positive definite")
    return sol[0]


def min_energy_block(
    J: Vec,
    M_a: Vec,
    m_b: Vec,
    v_d: Vec,
    qdot_null: Vec | None = None,
    singular_threshold: float = SINGULAR_THRESHOLD,
    max_damping: float = MAX_DAMPING,
) -> TaskSolve:
    """:func:`min_energy` for ``M = blockdiag(M_a (n, n), diag(m_b) (3,))``, J (6, n + 3)
    (the arm's columns first, the base's three last; ``n = 6``, fewer for a subset of
    the arm's joints).  Returns the (n + 3,) solution as ``x`` (NaN if ``M_a`` is not
    positive definite) plus the eigenvalue range of ``J M^-1 J^T``.

    The block structure costs nothing to exploit at this size: what costs is the number
    of numpy/LAPACK calls (each a few thousand instructions), so ``M`` is written out
    and solved whole.
    """
    n = M_a.shape[0]
    M = np.zeros((n + 3, n + 3), order="F")
    M[:n, :n] = M_a
    M.ravel(order="K")[n * (n + 4)::n + 4] = m_b  # the base's diagonal
    sol = _min_energy(J, M, v_d, qdot_null, singular_threshold, max_damping, 1)
    if sol is None:
        return TaskSolve(np.full(n + 3, np.nan), float("nan"), float("nan"), 0.0)
    return TaskSolve(*sol)


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
    x, lam_min, lam_max, delta = _damped(J.dot(J.T), J.dot(z), threshold, max_damping)
    return TaskSolve(z - J.T.dot(x), lam_min, lam_max, delta)


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
    jtw = J.T * wa if wa.ndim == 1 else J.T.dot(wa)
    h = jtw.dot(J)
    if wb.ndim == 1:
        h.ravel()[::n + 1] += wb  # the diagonal (h is contiguous: ravel is a view)
    else:
        h = h + wb
    out = solve_spd(h, jtw.dot(_as_vec(v_d)))
    if qdot_null is not None:
        out += null_project(J, _as_vec(qdot_null), singular_threshold, max_damping).x
    return out
