"""IDK strategies behind one interface: ``strategy.solve(problem) -> qdot (9,)``.

* :class:`MinEnergy` -- the paper's minimum kinetic energy + dynamically consistent
  null-space term (block-diagonal M, or the coupled M with ``robot.full_inertia``);
* :class:`Locomotion` -- the benchmark's damped weighted least squares (eq. 7) with
  the Euclidean null-space projector;
* :class:`Manipulation` -- base locked, the same damped least squares on the arm
  Jacobian J_a alone (square: no null space left);
* :class:`ConstrainedMinEnergy` -- beyond the paper: the min-energy objective with
  joint position/velocity/acceleration limits (and base speed/acceleration boxes) as
  hard bounds, a 9-variable box QP solved by :func:`mmctl.control.qp.box_qp`.

The *switch* benchmark is not a solver of its own: the controller (:mod:`.step`)
runs :class:`Manipulation` or :class:`Locomotion` and cross-fades between them.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import ClassVar, NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.control.idk import (
    _min_energy,
    min_energy,
    min_energy_block,
    solve_spd,
    weighted_dls,
)
from mmctl.control.limits import AVOID_SHARE, Limits
from mmctl.control.qp import box_qp
from mmctl.model.robot import Kinematics

Vec = NDArray[np.float64]


class Problem(NamedTuple):
    """One IDK problem.

    kin: the model evaluated at q; v_d: (6,) desired twist, control frame;
    q: (9,) configuration; qdot_prev: (9,) previous command; dt: period [s];
    z: (9,) secondary-task velocity ``G (q_des - q)`` (projected by each strategy).
    """

    kin: Kinematics
    v_d: Vec
    q: Vec
    qdot_prev: Vec
    dt: float
    z: Vec


class IdkStrategy(ABC):
    """A way to turn a desired twist into whole-body velocities."""

    name: ClassVar[str]

    @abstractmethod
    def solve(self, p: Problem) -> Vec:
        """Joint velocities (9,): arm [rad/s], base twist in the base frame."""


def hand_over(x: Vec, lb: Vec, ub: Vec, J: Vec, v_d: Vec,
              resolve: Callable[[NDArray[np.bool_], Vec], Vec], rounds: int = 3) -> Vec:
    """Joint-limit avoidance by hand-over: the coordinates of ``x`` (9,) beyond their
    bounds are pinned at the bound, and the task ``J x = v_d`` is solved again on the
    others (``resolve(free, rhs)`` -> x_free, with ``rhs = v_d - J_pinned x_pinned``):
    the base and the other joints take over the pinned joints' share of the motion.
    Repeated while the new solution crosses other bounds (``rounds`` at most); what is
    still out of bounds then is clipped (the limits scale the command after)."""
    return _hand_over(x, lb.tolist(), ub.tolist(), J, v_d, resolve, rounds)


def _hand_over(x: Vec, lo: list[float], hi: list[float], J: Vec, v_d: Vec,
               resolve: Callable[[NDArray[np.bool_], Vec], Vec], rounds: int = 3) -> Vec:
    """:func:`hand_over` with the bounds as lists (``lo <= hi``): the bookkeeping on
    nine numbers in Python floats, where numpy's cost per call would be most of the
    time (one resolve costs about what the whole solve does)."""
    tol = 1e-12
    n = len(lo)
    pinned: dict[int, float] = {}  # coordinate -> its bound, where it is pinned
    xs = x.tolist()
    for _ in range(rounds):
        crossed = False
        for i, v in enumerate(xs):
            if v < lo[i] - tol:
                pinned[i], crossed = lo[i], True
            elif v > hi[i] + tol:
                pinned[i], crossed = hi[i], True
        if not crossed:
            return x
        if n - len(pinned) < 6:
            break
        idx = tuple(sorted(pinned))
        x_pinned = np.zeros(n)
        for i in idx:
            x_pinned[i] = pinned[i]
        xs = resolve(_free_mask(n, idx), v_d - J.dot(x_pinned)).tolist()
        for i in idx:
            xs.insert(i, pinned[i])
        x = np.array(xs)
    return np.array([min(max(v, a), b) for v, a, b in zip(xs, lo, hi)])  # np.clip


_FREE_MASKS: dict[tuple[int, tuple[int, ...]], NDArray[np.bool_]] = {}


def _free_mask(n: int, pinned: tuple[int, ...]) -> NDArray[np.bool_]:
    """The (read-only) mask of the ``n`` coordinates but ``pinned``, made once each."""
    mask = _FREE_MASKS.get((n, pinned))
    if mask is None:
        mask = np.ones(n, dtype=bool)
        mask[list(pinned)] = False
        mask.setflags(write=False)
        _FREE_MASKS[(n, pinned)] = mask
    return mask


class _Avoidance:
    """:meth:`Limits.avoidance_bounds` in plain floats, and ``lb <= x <= ub`` against
    them: the same expressions, so the same numbers and the same answer (NaN is out).

    Most cycles are inside, and for them the bounds' arrays and their comparisons cost
    more than the whole min-energy solve; :meth:`inside` computes a joint's bound only in
    the direction it moves.  Construction checks the numbers against ``limits``'s own
    at probe poses, so the two cannot drift apart unnoticed.
    """

    def __init__(self, limits: Limits) -> None:
        self.margin = limits.margin
        self.q_max = limits.q_max.tolist()
        self.q_min = limits.q_min.tolist()
        self.two_a = [AVOID_SHARE * t for t in limits._two_ab]
        margin = self.margin
        for q_a in ([0.0] * 6, *(
                [f * q_max + (1.0 - f) * q_min for q_max, q_min in zip(self.q_max, self.q_min)]
                for f in (-0.1, 0.0, 0.01, 0.3, 0.5, 0.97, 1.0, 1.1)),
                [q - margin for q in self.q_max], [q + margin for q in self.q_min]):
            lb, ub = limits.avoidance_bounds(q_a)
            if self.bounds(q_a) != (lb.tolist(), ub.tolist()):
                raise RuntimeError("strategies._Avoidance does not compute what "
                                   "Limits.avoidance_bounds computes: change both")

    def bounds(self, q_a: list[float]) -> tuple[list[float], list[float]]:
        """(9,), (9,) lists: :meth:`Limits.avoidance_bounds` at ``q_a`` (6,) [rad]."""
        margin = self.margin
        lo = [-math.inf] * 9
        hi = [math.inf] * 9
        for i, (q, q_max, q_min, two_a) in enumerate(
                zip(q_a, self.q_max, self.q_min, self.two_a)):
            r = q_max - margin - q
            hi[i] = 0.0 if r <= 0.0 else math.sqrt(two_a * r)
            r = q - q_min - margin
            lo[i] = -(0.0 if r <= 0.0 else math.sqrt(two_a * r))
        return lo, hi

    def inside(self, q_a: list[float], x: list[float]) -> bool:
        """True if ``x`` (9,) is within the bounds at ``q_a`` (6,) [rad]."""
        margin, isnan = self.margin, math.isnan
        for v, q, q_max, q_min, two_a in zip(x, q_a, self.q_max, self.q_min, self.two_a):
            if v > 0.0:
                r = q_max - margin - q
                if r <= 0.0 or v > math.sqrt(two_a * r):
                    return False
            elif v < 0.0:
                r = q - q_min - margin
                if r <= 0.0 or v < -math.sqrt(two_a * r):
                    return False
            elif isnan(v):
                return False
        # the base is unbounded: only NaN is out
        return not (isnan(x[6]) or isnan(x[7]) or isnan(x[8]))


class MinEnergy(IdkStrategy):
    """``q* = J_M# v_d + (I - J_M# J) z`` (paper Property 1 and eq. 12-13); with
    ``limits`` (``idk.avoid_joint_limits``) a joint nearing its position limit hands its
    motion over (:func:`hand_over`: min-energy on the other coordinates)."""

    name = "min-energy"

    def __init__(self, cfg: Config, limits: Limits | None = None) -> None:
        self.thr = cfg.idk.singular_threshold
        self.damp = cfg.idk.max_damping
        self.full = cfg.robot.full_inertia
        self.limits = limits if cfg.idk.avoid_joint_limits else None
        self._avoid = _Avoidance(self.limits) if self.limits is not None else None

    def solve(self, p: Problem) -> Vec:
        k = p.kin
        x = self._whole(k, p.v_d, p.z)
        if self._avoid is None:
            return x
        q_a = p.q[:6].tolist()
        if self._avoid.inside(q_a, x.tolist()):
            return x
        lo, hi = self._avoid.bounds(q_a)
        M = self._inertia(k)

        def resolve(free: NDArray[np.bool_], rhs: Vec) -> Vec:
            return self._weighted(k.J.compress(free, 1),
                                  M.compress(free, 0).compress(free, 1), rhs, p.z[free])

        return _hand_over(x, lo, hi, k.J, p.v_d, resolve)

    def _whole(self, k: Kinematics, v_d: Vec, z: Vec) -> Vec:
        """The solve on every coordinate (block form unless ``robot.full_inertia``)."""
        if self.full and k.M_full is not None:
            return self._weighted(k.J, k.M_full, v_d, z)
        return min_energy_block(k.J, k.M_a, k.M_b, v_d, z, self.thr, self.damp).x

    def _weighted(self, J: Vec, M: Vec, v_d: Vec, z: Vec) -> Vec:
        """``J_M# v_d + P z`` with a dense weighting ``M`` on the columns of ``J``
        (:func:`min_energy` without its input conversions)."""
        sol = _min_energy(J, M, v_d, z, self.thr, self.damp, 0)
        if sol is None:
            raise ValueError("M must be symmetric positive definite")
        return sol[0]

    def _inertia(self, k: Kinematics) -> Vec:
        if self.full and k.M_full is not None:
            return k.M_full
        M = np.zeros((9, 9))
        M[:6, :6] = k.M_a
        M[6, 6], M[7, 7], M[8, 8] = k.M_b
        return M


class Locomotion(IdkStrategy):
    """``(J^T W_a J + W_b)^-1 J^T W_a v_d + (I - J# J) z`` (paper eq. 7); with ``limits``
    a joint nearing its position limit hands its motion over (:func:`hand_over`: the
    same weighted least squares on the other coordinates)."""

    name = "locomotion"

    def __init__(self, cfg: Config, limits: Limits | None = None) -> None:
        self.wa = np.array(cfg.idk.locomotion.w_alpha)
        self.wb = np.array(cfg.idk.locomotion.w_beta)
        self.thr = cfg.idk.singular_threshold
        self.damp = cfg.idk.max_damping
        self.limits = limits if cfg.idk.avoid_joint_limits else None
        self._avoid = _Avoidance(self.limits) if self.limits is not None else None

    def solve(self, p: Problem) -> Vec:
        J = p.kin.J
        x = weighted_dls(J, p.v_d, self.wa, self.wb, p.z,
                         singular_threshold=self.thr, max_damping=self.damp)
        if self._avoid is None:
            return x
        q_a = p.q[:6].tolist()
        if self._avoid.inside(q_a, x.tolist()):
            return x
        lo, hi = self._avoid.bounds(q_a)

        def resolve(free: NDArray[np.bool_], rhs: Vec) -> Vec:
            return weighted_dls(J.compress(free, 1), rhs, self.wa, self.wb[free], p.z[free],
                                singular_threshold=self.thr, max_damping=self.damp)

        return _hand_over(x, lo, hi, J, p.v_d, resolve)


class Manipulation(IdkStrategy):
    """Base locked: damped least squares on J_a with the arm part of W_beta."""

    name = "manipulation"

    def __init__(self, cfg: Config) -> None:
        self.wa = np.array(cfg.idk.locomotion.w_alpha)
        self.wb = np.array(cfg.idk.locomotion.w_beta[:6])
        self.thr = cfg.idk.singular_threshold
        self.damp = cfg.idk.max_damping

    def solve(self, p: Problem) -> Vec:
        out = np.zeros(9)
        out[:6] = weighted_dls(p.kin.J[:, :6], p.v_d, self.wa, self.wb, p.z[:6],
                               singular_threshold=self.thr, max_damping=self.damp)
        return out


class ConstrainedMinEnergy(IdkStrategy):
    """``min |qd - z|_M^2 / 2`` s.t. ``J qd = v_d`` and box bounds on qd.

    Without an active bound the minimiser is exactly :class:`MinEnergy`'s solution
    (it is the M-closest point to z on the task manifold), and that solution is
    returned as is.  Otherwise the task becomes the stiff penalty
    ``rho |J qd - v_d|^2 / 2`` (``idk.constrained.task_weight``) so the QP stays
    feasible when the bounds cannot produce v_d, and the box QP is solved by active
    set, warm-started from the clipped unconstrained solution.  A polish step then
    re-solves the exact task on the free coordinates with the active bounds fixed.
    """

    name = "constrained-min-energy"

    def __init__(self, cfg: Config, limits: Limits) -> None:
        self.unconstrained = MinEnergy(cfg)
        self.limits = limits
        self.rho = cfg.idk.constrained.task_weight
        self.max_iter = cfg.idk.constrained.max_iter
        self.last_iterations = 0

    def bounds(self, p: Problem) -> tuple[Vec, Vec]:
        """The (9,), (9,) bounds on qdot for this cycle."""
        return self.limits.box_bounds(p.q, p.qdot_prev, p.dt)

    def solve(self, p: Problem) -> Vec:
        x = self.unconstrained.solve(p)
        lb, ub = self.bounds(p)
        if bool(np.all(x >= lb)) and bool(np.all(x <= ub)):
            self.last_iterations = 0
            return x
        k = p.kin
        if k.M_full is not None and self.unconstrained.full:
            H = k.M_full.copy()
        else:
            H = np.zeros((9, 9))
            H[:6, :6] = k.M_a
            H[6, 6], H[7, 7], H[8, 8] = k.M_b
        g = -(H @ p.z) - self.rho * (k.J.T @ p.v_d)
        res = box_qp(H + self.rho * (k.J.T @ k.J), g, lb, ub, x0=x, max_iter=self.max_iter)
        self.last_iterations = res.iterations
        return self._polish(H, k.J, p, res.x, res.active != 0, lb, ub)

    def _polish(self, M: Vec, J: Vec, p: Problem, x: Vec, act: NDArray[np.bool_],
                lb: Vec, ub: Vec) -> Vec:
        """With the active set found, solve the *exact* task on the free variables.

        ``min |x_F - z|_M`` s.t. ``J_F x_F = v_d - J_A x_A`` (a min-energy problem on the
        free coordinates); kept if it stays in the box and tracks v_d at least as well.
        """
        free = ~act
        if int(free.sum()) < 6:
            return x
        x_a = x[act]
        M_ff = M[np.ix_(free, free)]
        z_f = p.z[free] + solve_spd(M_ff, M[np.ix_(free, act)] @ (p.z[act] - x_a))
        r = p.v_d - J[:, act] @ x_a
        x_f = min_energy(J[:, free], M_ff, r, z_f,
                         singular_threshold=self.unconstrained.thr,
                         max_damping=self.unconstrained.damp)
        out = x.copy()
        out[free] = x_f
        tol = 1e-12
        if not (np.all(out >= lb - tol) and np.all(out <= ub + tol)):
            return x
        if np.abs(J @ out - p.v_d).max() > np.abs(J @ x - p.v_d).max():
            return x
        return np.clip(out, lb, ub)


def make_strategies(cfg: Config, limits: Limits) -> dict[str, IdkStrategy]:
    """The four solvers by name (``min-energy``, ``locomotion``, ``manipulation``,
    ``constrained-min-energy``)."""
    items: list[IdkStrategy] = [
        MinEnergy(cfg, limits), Locomotion(cfg, limits), Manipulation(cfg),
        ConstrainedMinEnergy(cfg, limits)
    ]
    return {s.name: s for s in items}
