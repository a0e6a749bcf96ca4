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
    active: NDArray[np.int8] | None = None,
) -> BoxQpResult:
    """Solve the box QP above.

    x0: (n,) starting guess (projected on the box; default the unconstrained
    minimiser); active: a working set to start from (e.g. the previous cycle's), by
    default the bounds that clipping ``x0`` touched.  The bookkeeping is plain Python
    (n is small); numpy only does the products and the Cholesky solves.
    """
    n = g.shape[0]
    if x0 is None:
        x0 = solve_spd(H, -g)
    x = np.clip(x0, lb, ub)
    lo, hi = lb.tolist(), ub.tolist()
    xs = x.tolist()
    if active is not None:
        st = [int(a) for a in active.tolist()]
        for i in range(n):
            if st[i] < 0:
                xs[i] = lo[i]
            elif st[i] > 0:
                xs[i] = hi[i]
    else:
        st = [-1 if xs[i] <= lo[i] else (1 if xs[i] >= hi[i] else 0) for i in range(n)]
    equal = [lo[i] == hi[i] for i in range(n)]
    for i in range(n):
        if equal[i]:
            st[i], xs[i] = -1, lo[i]
    gl = g.tolist()
    scale = max(1.0, max(abs(v) for v in gl))
    at_min = False  # xs minimises over the current free set (skip the re-solve)
    for it in range(1, max_iter + 1):
        free = [i for i in range(n) if st[i] == 0]
        if free and not at_min:
            xa = np.array(xs)
            fixed_part = xa.copy()
            fixed_part[free] = 0.0
            rhs = -(g + H @ fixed_part)
            target = solve_spd(H.take(free, 0).take(free, 1), rhs[free]).tolist()
            # ratio test: the largest step in [0, 1] toward target inside the box
            alpha, block, side = 1.0, -1, 0
            for k, i in enumerate(free):
                p = target[k] - xs[i]
                if p > 0.0 and xs[i] + p > hi[i]:
                    a = (hi[i] - xs[i]) / p
                    if a < alpha:
                        alpha, block, side = a, i, 1
                elif p < 0.0 and xs[i] + p < lo[i]:
                    a = (lo[i] - xs[i]) / p
                    if a < alpha:
                        alpha, block, side = a, i, -1
            if block < 0:
                for k, i in enumerate(free):
                    xs[i] = target[k]
                at_min = True
                continue
            alpha = max(alpha, 0.0)
            for k, i in enumerate(free):
                xs[i] += alpha * (target[k] - xs[i])
            xs[block] = hi[block] if side > 0 else lo[block]
            st[block] = side
            continue
        at_min = False
        grad = (H @ np.array(xs) + g).tolist()
        worst, worst_m = -1, -tol * scale
        for i in range(n):
            if st[i] == 0 or equal[i]:
                continue
            m = grad[i] if st[i] < 0 else -grad[i]
            if m < worst_m:
                worst, worst_m = i, m
        if worst < 0:
            return BoxQpResult(np.array(xs), it, True, np.array(st, dtype=np.int8))
        st[worst] = 0
    x = np.clip(np.array(xs), lb, ub)
    return BoxQpResult(x, max_iter, False, np.array(st, dtype=np.int8))
