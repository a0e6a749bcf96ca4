"""Self-collision avoidance: the robot is never pushed into its own body.

Every cycle the controller measures the distance of each pair of the robot's parts
that can meet (:data:`mmctl.model.geometry.PAIRS`: coal through Pinocchio's
``GeometryModel``, about 10 us for all of them) and, for the pairs nearer than
``collision_margin`` + :data:`WATCH` [m], the distance's rate along the command:
``d' = n . (J_p2 - J_p1) qdot_arm``, with ``n`` the unit vector from the first part's
nearest point ``p1`` to the second's ``p2`` and ``J_p`` the linear Jacobian of a point
fixed to its link.  The base's motion moves both parts alike (the deck is on the base),
so only the arm's joints change a distance.

A command that closes a pair is scaled, as a whole, so that the closing speed stays on
the braking curve ``min(sqrt(2 k a room), room / tau)`` (``room = d - margin``; ``k``:
metres per radian of the command's fastest joint; ``a``: 80 % of the joints'
acceleration limit; ``tau`` 50 ms): the same curve as the singularity braking, so the
pair comes to rest at the margin within the acceleration limits.  Moving apart, and
moving along (``d' >= 0``), are free: a robot inside the margin can always be pulled
out.  A pair nearer than ``margin - collision_tolerance`` is the ``self_collision``
fault (and enabling is refused while it lasts): the braking cannot get there unless the
robot is moved otherwise (from the pendant, or it started there).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.model.geometry import BodyModel
from mmctl.model.robot import RobotModel

Vec = NDArray[np.float64]

#: pairs nearer than the margin plus this [m] get their rate computed each cycle
WATCH = 0.15
#: the longest lever of a joint over a point of the arm [m] (the UR10e's reach, 1.3 m,
#: plus the handle), for the watch distance at speed
LEVER = 1.5
#: the shortest look-ahead along the command [rad of its fastest joint]
AHEAD = 0.01
#: [m] over the look-ahead, what the gradient mispredicts by less than this is its
#: curvature, not a part it does not see
UNSEEN = 0.001
#: a command turned further than this (cos of the angle) from the measure's is measured
#: again
TURN_COS = 0.95
#: the distances are measured again after the arm turned this much in all [rad] ...
RECHECK_ANGLE = 0.01
#: ... or after this many cycles
RECHECK_CYCLES = 10
#: the braking curve's exponential end [s] (as the singularity braking's)
TAU = 0.05
_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_Z6 = np.zeros(6)
_Z6.setflags(write=False)


class Near(NamedTuple):
    """A pair nearer than the watch distance: its names, distance [m] and the
    distance's gradient in the arm's joints (6,) [m/rad]."""

    pair: tuple[str, str]
    distance: float
    grad: tuple[float, ...]
    ahead: float = 0.0
    """How much more the distance falls along the command of the measure than its
    gradient predicts, per radian of the fastest joint over the look-ahead [m/rad] (0:
    the gradient sees it all)."""


class BodyState(NamedTuple):
    """The last measure: the arm's joints then, the controller's cycle, the watched
    pairs, and the nearest pair of all with its distance [m]."""

    q: tuple[float, ...]
    cycle: int
    near: tuple[Near, ...]
    pair: tuple[str, str] | None
    distance: float
    watch: float
    direction: tuple[float, ...] | None = None
    """The command's direction at the measure (unit length; None: at rest)."""


class BodyBrake(NamedTuple):
    """One cycle's verdict: ``scale`` of the command (1: free), the nearest pair and its
    distance [m], and ``fault`` when a pair is deeper than the margin's tolerance."""

    scale: float
    pair: tuple[str, str] | None
    distance: float
    fault: bool
    qdot_arm: Vec | None = None
    """The arm's rates with each pair's closing part taken out (None: unchanged); the
    whole command is then scaled by ``scale``."""


class BodyCheck:
    """The robot's self-collision check and braking (see the module docstring)."""

    def __init__(self, cfg: Config, model: RobotModel) -> None:
        self.body = BodyModel(cfg.robot, model.arm, model.mount)
        self.margin = cfg.safety.collision_margin
        self.floor = cfg.safety.collision_margin - cfg.safety.collision_tolerance
        self.watch = self.margin + WATCH
        self.brake_accel = 0.8 * min(min(cfg.limits.joint_acceleration),
                                     cfg.arm.speedj_acceleration)
        geom = self.body.geom
        self._joints = tuple((geom.geometryObjects[p.first].parentJoint,
                              geom.geometryObjects[p.second].parentJoint)
                             for p in geom.collisionPairs)

    def near(self, q_a: Vec, watch: float | None = None, qdot_arm: Vec | None = None
             ) -> tuple[list[Near], tuple[str, str] | None, float]:
        """The pairs nearer than ``watch`` [m] (default: the margin plus :data:`WATCH`)
        at ``q_a`` (6,) with their gradients and, along ``qdot_arm``, how much they close
        over the look-ahead (:attr:`Near.ahead`); and the nearest pair of all at ``q_a``
        with its distance [m]."""
        near, pair, dist = self._measure(q_a, self.watch if watch is None else watch)
        if qdot_arm is not None:
            near = self._look_ahead(q_a, qdot_arm.tolist(), near)
        return near, pair, dist

    def _measure(self, q_a: Vec, watch: float
                 ) -> tuple[list[Near], tuple[str, str] | None, float]:
        body = self.body
        model, data = body.model, body.data
        # a fresh GeometryData each time: coal's solvers keep their last answer as the next
        # one's start, which moves a GJK distance in its 7th digit (the update is pure)
        gdata = pin.GeometryData(body.geom)
        k = pin.computeDistances(model, data, body.geom, gdata, q_a)
        results = gdata.distanceResults
        dists = [r.min_distance for r in results]
        out: list[Near] = []
        jacobians: dict[int, Vec] = {}
        for i, d in enumerate(dists):
            if d >= watch:
                continue
            if not jacobians:
                pin.computeJointJacobians(model, data, q_a)
            res = results[i]
            n = res.normal.tolist()
            j1, j2 = self._joints[i]
            g = (self._point_grad(j2, res.getNearestPoint2(), n, jacobians)
                 - self._point_grad(j1, res.getNearestPoint1(), n, jacobians))
            out.append(Near(body.pairs[i], float(d), tuple(g.tolist())))
        return out, body.pairs[k], float(dists[k])

    def _look_ahead(self, q_a: Vec, qd: list[float], near: list[Near]) -> list[Near]:
        """``near`` with :attr:`Near.ahead` along ``qd``.  The look-ahead sees what the
        gradient cannot: a distance is the smaller of its parts' (a capsule's end and
        its side), and while one part is nearest the other may close fast (an upper arm
        turning about the shoulder over the deck).  It goes as far as the fastest joint
        turns while braking (and 1.5 times that), at least :data:`AHEAD` [rad]."""
        speed = max(map(abs, qd))
        if speed <= 0.0 or not near:
            return near
        theta = max(AHEAD, 1.5 * speed * speed / (2.0 * self.brake_accel))
        body = self.body
        gdata = pin.GeometryData(body.geom)  # (fresh: as in _measure)
        pin.computeDistances(body.model, body.data, body.geom, gdata,
                             q_a + np.array(qd) * (theta / speed))
        ahead = [r.min_distance for r in gdata.distanceResults]
        index = {p: i for i, p in enumerate(body.pairs)}
        step = [x * (theta / speed) for x in qd]
        out = []
        for n in near:
            # what the gradient does not predict (a part that becomes the nearest); its
            # curvature alone (a millimetre over the look-ahead) is not that
            predicted = n.distance + sum(g * x for g, x in zip(n.grad, step))
            unseen = predicted - ahead[index[n.pair]] - UNSEEN
            out.append(n._replace(ahead=max(0.0, unseen / theta)))
        return out

    def _point_grad(self, joint: int, p: Vec, n: list[float], cache: dict[int, Vec]) -> Vec:
        """(6,) ``n . J_p``: the rate along ``n`` of the point ``p`` (base_link) fixed to
        ``joint`` per arm joint rate.  With ``v_p = v_o + w x r`` (``r = p - o``),
        ``n . v_p = n . v_o + (r x n) . w``: two products, no (3, 6) matrix."""
        if joint == 0:
            return _Z6
        J = cache.get(joint)
        if J is None:
            J = pin.getJointJacobian(self.body.model, self.body.data, joint, _LWA)
            cache[joint] = J
        ox, oy, oz = self.body.data.oMi[joint].translation.tolist()
        rx, ry, rz = p[0] - ox, p[1] - oy, p[2] - oz
        nx, ny, nz = n
        rn = np.array((ry * nz - rz * ny, rz * nx - rx * nz, rx * ny - ry * nx))
        grad: Vec = np.array(n).dot(J[:3]) + rn.dot(J[3:])
        return grad

    def brake(self, st: BodyState | None, q_a: Vec, qdot_arm: Vec, cycle: int
              ) -> tuple[BodyState, BodyBrake]:
        """The command's scale at ``q_a`` (6,) for the arm's joint rates ``qdot_arm``,
        and the check's new state (``cycle``: the controller's cycle count).

        The distances are measured (:meth:`near`) when the arm has turned by more than
        :data:`RECHECK_ANGLE` in all since the last measure, or :data:`RECHECK_CYCLES`
        cycles later; in between each watched pair's distance is its measure plus its
        gradient times the joints' change (first order: off by less than 0.1 mm over
        0.01 rad), and a pair outside the watch distance cannot close its 0.15 m."""
        ql = q_a.tolist()
        qd = qdot_arm.tolist()
        speed = max(map(abs, qd))
        # watch every pair that could close its room at this speed before the braking
        # stops it: a joint's stopping angle times the longest lever
        reach = LEVER * speed * speed / (2.0 * self.brake_accel)
        watch = self.margin + WATCH + reach
        fresh = (st is None or cycle - st.cycle >= RECHECK_CYCLES or cycle < st.cycle
                 or watch > st.watch
                 or sum(abs(a - b) for a, b in zip(ql, st.q)) > RECHECK_ANGLE)
        dq = None if st is None else [a - b for a, b in zip(ql, st.q)]
        if not fresh:
            assert st is not None
            verdict = self._verdict(st, qd, dq, speed)
            fresh = _turned(st.direction, _unit(verdict[0]))
        if fresh:
            watch += 0.5 * reach  # room to speed up before the next measure
            near, pair, dist = self._measure(q_a, watch)
            st = BodyState(tuple(ql), cycle, tuple(near), pair, dist, watch)
            # the look-ahead along the command as the gradients leave it
            fixed = self._verdict(st, qd, None, speed)[0]
            st = st._replace(near=tuple(self._look_ahead(q_a, fixed, near)),
                             direction=_unit(fixed))
            dq = None
            verdict = self._verdict(st, qd, None, speed)
        assert st is not None
        fixed, scale, pair, dist = verdict
        if dist < self.floor:
            return st, BodyBrake(0.0, pair, dist, True)
        arm = None if fixed == qd else np.array(fixed)
        return st, BodyBrake(scale, pair, dist, False, arm)

    def _verdict(self, st: BodyState, qd: list[float], dq: list[float] | None, speed: float
                 ) -> tuple[list[float], float, tuple[str, str] | None, float]:
        """The arm's rates with each watched pair's closing part taken out, the scale
        for what only the look-ahead sees, and the pair to report with its distance
        (the binding one, else the nearest)."""
        pair, dist = st.pair, st.distance
        scale = 1.0
        binding: tuple[tuple[str, str] | None, float] | None = None
        fixed = qd
        # nearest first: the part of the command that closes a pair faster than its
        # braking curve allows is taken out along the pair's gradient (as a wall takes
        # the part into it out: the rest of the motion, and the base, stay)
        for n in sorted(st.near, key=lambda n: n.distance):
            g = n.grad
            d = n.distance if dq is None else n.distance + sum(x * y for x, y in zip(g, dq))
            if d < dist:
                pair, dist = n.pair, d
            closing = -sum(x * y for x, y in zip(g, fixed))  # > 0: closing [m/s]
            ahead = n.ahead * speed  # what only the look-ahead sees closing [m/s]
            rate = max(closing, 0.0) + ahead
            if rate <= 0.0:
                continue
            room = d - self.margin
            if room <= 0.0:
                allowed = 0.0
            else:
                k = rate / speed
                allowed = min(math.sqrt(2.0 * k * self.brake_accel * room), room / TAU)
            gg = sum(x * x for x in g)
            if closing > allowed and gg > 1e-12:
                c = (closing - allowed) / gg
                fixed = [x + c * y for x, y in zip(fixed, g)]
                binding = binding or (n.pair, d)
            if ahead > 0.0:  # not in the gradient: slow the whole command
                after = max(-sum(x * y for x, y in zip(g, fixed)), 0.0) + ahead
                if after > allowed:
                    s = allowed / after
                    if s < scale:
                        scale, binding = s, (n.pair, d)
        if binding is not None:
            pair, dist = binding
        return fixed, scale, pair, dist

    def inside(self, q_a: Vec) -> tuple[tuple[str, str], float] | None:
        """The nearest pair and its distance when it is deeper than the tolerance allows
        (enabling is refused there), else None."""
        _, pair, dist = self._measure(q_a, -math.inf)  # (no pair watched: no gradients)
        return (pair, dist) if pair is not None and dist < self.floor else None


def _turned(before: tuple[float, ...] | None, now: tuple[float, ...] | None) -> bool:
    """True when the command's direction is no longer the measure's (its look-ahead
    would look the wrong way): started, stopped, or turned by more than ~18 deg."""
    if before is None or now is None:
        return before is not now
    return sum(a * b for a, b in zip(before, now)) < TURN_COS


def _unit(v: list[float]) -> tuple[float, ...] | None:
    norm = math.sqrt(sum(x * x for x in v))
    return None if norm == 0.0 else tuple(x / norm for x in v)
