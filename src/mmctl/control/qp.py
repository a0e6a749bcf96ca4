"""A small dense box-constrained QP solver (primal active set), for the 2 ms cycle.

    minimise  x^T H x / 2 + g^T x   subject to  lb <= x <= ub

with ``H`` (n, n) symmetric positive definite and n ~ 10.  Starting from the
projection of the unconstrained minimiser onto the box (optionally a warm-start
working set), each iteration solves the equality problem on the free variables
(Cholesky), steps to the first blocking bound, and releases the bound with the most
negative multiplier when no step is possible.  Strictly convex problems terminate
in finitely many iterations; typical problems here take 1-4.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.control.idk import solve_spd

Vec = NDArray[np.float64]


class BoxQpResult(NamedTuple):
    """Solution ``x`` (n,), iterations used, whether optimality was reached, and the
    final working set as a (n,) int8 array (-1 at lb, +1 at ub, 0 free)."""

    x: Vec
    iterations: int
    converged: bool
    active: NDArray[np.int8]


def box_qp(
    H: Vec,
    g: Vec,
    lb: Vec,
    ub: Vec,
    x0: Vec | None = None,
    max_iter: int = 50,
    tol: float = 1e-12,
) -> BoxQpResult:
    """Solve the box QP above; ``x0`` (n,) is a starting guess (projected on the box)."""
    n = g.shape[0]
    if x0 is None:
        x0 = solve_spd(H, -g)
    x = np.clip(x0, lb, ub)
    state = np.zeros(n, dtype=np.int8)
    state[x <= lb] = -1
    state[x >= ub] = 1
    equal = lb == ub
    state[equal] = -1
    scale = max(1.0, float(np.max(np.abs(g))))
    at_min = False  # x minimises over the current free set (skip the re-solve)
    for it in range(1, max_iter + 1):
        free = state == 0
        if free.any() and not at_min:
            fixed = ~free
            rhs = -g[free]
            if fixed.any():
                rhs = rhs - H[np.ix_(free, fixed)] @ x[fixed]
            target = solve_spd(H[np.ix_(free, free)], rhs)
            p = target - x[free]
        else:
            p = np.zeros(0)
        if at_min or p.size == 0:
            at_min = False
            grad = H @ x + g
            mult = np.where(state == -1, grad, np.where(state == 1, -grad, 0.0))
            mult[equal] = 0.0  # a variable with lb == ub can never be released
            worst = int(np.argmin(mult))
            if mult[worst] >= -tol * scale:
                return BoxQpResult(x, it, True, state)
            state[worst] = 0
            continue
        xf = x[free]
        # largest step in [0, 1] keeping the free variables in the box
        lbf, ubf = lb[free], ub[free]
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(p > 0, (ubf - xf) / p, np.where(p < 0, (lbf - xf) / p, np.inf))
        k = int(np.argmin(ratio))
        alpha = float(ratio[k])
        if alpha >= 1.0:
            x[free] = target
            at_min = True
            continue
        alpha = max(alpha, 0.0)
        xf = xf + alpha * p
        idx = np.flatnonzero(free)[k]
        xf[k] = ubf[k] if p[k] > 0 else lbf[k]
        x[free] = xf
        state[idx] = 1 if p[k] > 0 else -1
    return BoxQpResult(np.clip(x, lb, ub), max_iter, False, state)
