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

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import ClassVar, NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.control.idk import min_energy, min_energy_block, solve_spd, weighted_dls
from mmctl.control.limits import Limits
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
    tol = 1e-12
    pinned = np.zeros(x.shape[0], dtype=bool)
    for _ in range(rounds):
        out = (x < lb - tol) | (x > ub + tol)
        if not out.any():
            return x
        pinned |= out
        free = ~pinned
        if int(free.sum()) < 6:
            break
        x_p = np.clip(x, lb, ub)[pinned]
        x = x.copy()
        x[pinned] = x_p
        x[free] = resolve(free, v_d - J[:, pinned] @ x_p)
    return np.clip(x, lb, ub)


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

    def solve(self, p: Problem) -> Vec:
        k = p.kin
        x = self._whole(k, p.v_d, p.z)
        if self.limits is None:
            return x
        lb, ub = self.limits.avoidance_bounds(p.q[:6].tolist())
        if bool(np.all(x >= lb)) and bool(np.all(x <= ub)):
            return x
        M = self._inertia(k)

        def resolve(free: NDArray[np.bool_], rhs: Vec) -> Vec:
            return self._weighted(k.J[:, free], M[np.ix_(free, free)], rhs, p.z[free])

        return hand_over(x, lb, ub, k.J, p.v_d, resolve)

    def _whole(self, k: Kinematics, v_d: Vec, z: Vec) -> Vec:
        """The solve on every coordinate (block form unless ``robot.full_inertia``)."""
        if self.full and k.M_full is not None:
            return self._weighted(k.J, k.M_full, v_d, z)
        return min_energy_block(k.J, k.M_a, k.M_b, v_d, z, self.thr, self.damp).x

    def _weighted(self, J: Vec, M: Vec, v_d: Vec, z: Vec) -> Vec:
        """``J_M# v_d + P z`` with a dense weighting ``M`` on the columns of ``J``."""
        return min_energy(J, M, v_d, z, singular_threshold=self.thr, max_damping=self.damp)

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

    def solve(self, p: Problem) -> Vec:
        J = p.kin.J
        x = weighted_dls(J, p.v_d, self.wa, self.wb, p.z,
                         singular_threshold=self.thr, max_damping=self.damp)
        if self.limits is None:
            return x
        lb, ub = self.limits.avoidance_bounds(p.q[:6].tolist())
        if bool(np.all(x >= lb)) and bool(np.all(x <= ub)):
            return x

        def resolve(free: NDArray[np.bool_], rhs: Vec) -> Vec:
            return weighted_dls(J[:, free], rhs, self.wa, self.wb[free], p.z[free],
                                singular_threshold=self.thr, max_damping=self.damp)

        return hand_over(x, lb, ub, J, p.v_d, resolve)


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
