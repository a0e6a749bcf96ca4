"""Velocity, acceleration and position limits that keep the direction of ``qdot``.

``qdot`` (9,) = six arm joint rates [rad/s] and the base twist (vx, vy [m/s], wz
[rad/s]) in the base frame.  :meth:`Limits.apply` runs three stages:

1. **velocity**: ``qdot_v = s_v qdot_d`` with the largest ``s_v`` in [0, 1] such that
   every joint speed, the base linear speed |(vx, vy)| and yaw rate, every wheel
   speed (mecanum matrix) and the end-effector linear/angular speed (``J qdot``) are
   within their limits.  Joint position limits act as direction-dependent speed caps
   (:meth:`Limits.joint_caps`): the speed *toward* a limit is at most
   ``sqrt(2 a_b r)``, ``r`` the distance to the point ``position_margin`` inside the
   limit (zero from there on), ``a_b`` the braking deceleration (:data:`BRAKE_SHARE`
   of the joint's acceleration limit and of the speedJ acceleration the arm follows
   with): a joint moving toward its limit at full speed comes to rest inside the
   margin, whatever its speed, instead of overshooting the braking zone (at 180 deg/s
   and 4 rad/s^2 a joint needs 1.2 rad to stop).  Moving away is free.
   The whole-body caps of :mod:`mmctl.control.iso15066` join them: the kinetic energy
   ``E_K = 1/2 qdot_a' M_a qdot_a + 1/2 qdot_b' M_b qdot_b`` (the paper's block-diagonal
   M; given ``M_a``, ``M_b``) at most ``caps.energy`` (``s <= sqrt(E_max / E_K)``), the
   base's linear speed at most ``caps.base_speed`` and the end-effector's at most
   ``caps.ee_speed``.  :attr:`Limited.limit` names the cap that set ``s_v``.
2. **acceleration**: ``qdot = qdot_prev + s_a (qdot_v - qdot_prev)`` with the largest
   ``s_a`` in [0, 1] such that joint and base (linear |a_xy|, angular) accelerations
   are within limits over ``dt``.  The *change* keeps its direction; starting from
   rest the result is ``s_a s_v qdot_d`` (direction of ``qdot_d`` kept).  Since every
   velocity limit is a convex set containing ``qdot_prev`` and ``qdot_v``, the blend
   stays within the velocity limits.
3. **final**: the joint speed and position caps again on the result, so they hold even
   if ``qdot_prev`` was outside them (position braking has priority over the
   acceleration limit).  The other caps are not re-applied here: ``qdot_prev`` is
   outside them only when a cap was lowered at run time (the reduced profile), and the
   command then reaches the new cap on the acceleration limits, never by a jump.

Non-finite input gives zero velocity.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from mmctl.config.base import MecanumConfig
from mmctl.config.control import LimitsConfig
from mmctl.control.iso15066 import NO_CAPS, Caps
from mmctl.control.mecanum import wheel_matrix

Vec = NDArray[np.float64]

_INF = float("inf")

AVOID_SHARE = 0.25
"""Share of the braking deceleration the IDK's joint-limit avoidance plans with: it hands
a joint's motion to the others 4x farther from the rest point than the braking starts."""

BRAKE_SHARE = 0.8
"""Share of the acceleration limits the position braking plans with: the arm follows a
command one cycle late, the rest of the acceleration catches up with that."""


class Limited(NamedTuple):
    """Result of :meth:`Limits.apply`: the limited qdot (9,), the velocity scale s_v,
    the acceleration blend s_a and the final scale s_f (all in [0, 1]), and ``limit``:
    what bound the command ("" none; see :data:`LIMIT_NAMES`)."""

    qdot: Vec
    scale: float
    accel_scale: float
    final_scale: float
    limit: str = ""


#: What :attr:`Limited.limit` can name: the cap that set s_v (the first one reached),
#: else "acceleration" when the acceleration blend bound the command, else "".
LIMIT_NAMES: tuple[str, ...] = (
    "", "joint_speed", "joint_position", "base_speed", "base_yaw_rate", "wheel_speed",
    "ee_speed", "ee_angular_speed", "energy", "acceleration", "singularity", "wall",
    "self_collision")
"""(``singularity``: the controller's singularity braking, after the limits; ``wall``: a
virtual wall (:mod:`mmctl.control.walls`), before them, when no limit bound;
``self_collision``: the braking before the robot's own body (:mod:`mmctl.control.body`),
last.)"""


class Limits:
    """Joint/wheel/base/end-effector limits (see the module docstring)."""

    def __init__(self, lim: LimitsConfig, mecanum: MecanumConfig,
                 arm_acceleration: float | None = None, caps: Caps = NO_CAPS) -> None:
        """``arm_acceleration``: the speedJ acceleration [rad/s^2] the arm follows a
        command with (``arm.speedj_acceleration``); the position braking plans with
        :data:`BRAKE_SHARE` of the smaller of it and each joint's acceleration limit.
        ``caps``: the whole-body caps (energy, base and end-effector speed)."""
        self.cfg = lim
        self.caps = caps
        self.v_joint = np.array(lim.joint_velocity)
        self.a_joint = np.array(lim.joint_acceleration)
        self.q_min = np.array(lim.joint_position_min)
        self.q_max = np.array(lim.joint_position_max)
        self.margin = lim.position_margin
        self.v_lin = min(lim.base_linear_velocity, caps.base_speed)
        self.energy = caps.energy
        self.w_base = lim.base_angular_velocity
        self.a_lin = lim.base_linear_acceleration
        self.a_ang = lim.base_angular_acceleration
        self.wheel = lim.wheel_velocity
        self.ee_lin = min(lim.ee_linear_velocity, caps.ee_speed)
        self.ee_ang = lim.ee_angular_velocity
        self.W = wheel_matrix(mecanum)
        self._W = self.W.tolist()
        self._vj = self.v_joint.tolist()
        self._aj = self.a_joint.tolist()
        self._qmin = self.q_min.tolist()
        self._qmax = self.q_max.tolist()
        follow = _INF if arm_acceleration is None else arm_acceleration
        #: per joint: 2 a_b [rad/s^2] (the braking curve is v = sqrt(2 a_b r))
        self._two_ab = [2.0 * BRAKE_SHARE * min(a, follow) for a in self._aj]

    # --- position braking ------------------------------------------------------
    def joint_caps(self, q_a: list[float]) -> tuple[list[float], list[float]]:
        """Per arm joint, the largest speed [rad/s] toward its upper and toward its lower
        limit at ``q_a`` (6,): ``min(v_max, sqrt(2 a_b r))``, r the distance to the rest
        point ``position_margin`` inside the limit, 0 at or past it."""
        margin = self.margin
        up: list[float] = []
        down: list[float] = []
        for i in range(6):
            vj, two_ab = self._vj[i], self._two_ab[i]
            r = self._qmax[i] - margin - q_a[i]
            up.append(0.0 if r <= 0.0 else min(vj, math.sqrt(two_ab * r)))
            r = q_a[i] - self._qmin[i] - margin
            down.append(0.0 if r <= 0.0 else min(vj, math.sqrt(two_ab * r)))
        return up, down

    def avoidance_bounds(self, q_a: list[float]) -> tuple[Vec, Vec]:
        """(9,), (9,) bounds for the IDK's joint-limit avoidance: an arm joint's speed
        toward its limit at most ``sqrt(2 a r / AVOID_SHARE^-1)`` (the braking curve on
        :data:`AVOID_SHARE` of its deceleration: it starts 4x farther out), 0 at or past
        the rest point; no bound on the base or away from a limit."""
        margin = self.margin
        lb = np.full(9, -_INF)
        ub = np.full(9, _INF)
        for i in range(6):
            two_a = AVOID_SHARE * self._two_ab[i]
            r = self._qmax[i] - margin - q_a[i]
            ub[i] = 0.0 if r <= 0.0 else math.sqrt(two_a * r)
            r = q_a[i] - self._qmin[i] - margin
            lb[i] = -(0.0 if r <= 0.0 else math.sqrt(two_a * r))
        return lb, ub

    # --- joint boxes -----------------------------------------------------------
    def box_bounds(self, q: Vec, qdot_prev: Vec, dt: float) -> tuple[Vec, Vec]:
        """Per-coordinate bounds (9,), (9,) on qdot for one period ``dt`` [s]: speed,
        position braking and acceleration (box: |vx|, |vy| <= v_lin separately).

        If ``qdot_prev`` lies outside the speed box, the acceleration bound gives way
        (the bound is the point of the speed box nearest to ``qdot_prev``).
        """
        prev = qdot_prev.tolist()
        up, down = self.joint_caps(q[:6].tolist())
        lo = [-d for d in down]
        hi = list(up)
        lo += [-self.v_lin, -self.v_lin, -self.w_base]
        hi += [self.v_lin, self.v_lin, self.w_base]
        acc = [a * dt for a in self._aj] + [self.a_lin * dt] * 2 + [self.a_ang * dt]
        lb, ub = [], []
        for i in range(9):
            low, high = max(lo[i], prev[i] - acc[i]), min(hi[i], prev[i] + acc[i])
            if low > high:  # braking beats the acceleration limit
                low = high = min(max(prev[i], lo[i]), hi[i])
            lb.append(low)
            ub.append(high)
        return np.array(lb), np.array(ub)

    # --- scales ----------------------------------------------------------------
    def velocity_scale(self, qdot: Vec, q_a: Vec, J: Vec, M_a: Vec | None = None,
                       M_b: Vec | None = None) -> float:
        """Largest s in [0, 1] with s*qdot within every speed, position and whole-body
        cap (the energy cap only with ``M_a`` (6, 6) and ``M_b`` (3,))."""
        return self.velocity_scale_why(qdot, q_a, J, M_a, M_b)[0]

    def velocity_scale_why(self, qdot: Vec, q_a: Vec, J: Vec, M_a: Vec | None = None,
                           M_b: Vec | None = None) -> tuple[float, str]:
        """:meth:`velocity_scale` and the cap that set it ("" when s = 1)."""
        # plain floats: ~10x cheaper than numpy for 9-element vectors
        qd = qdot.tolist()
        s, why = self._joint_scale(qd, q_a)
        vx, vy, wz = qd[6], qd[7], qd[8]
        vb = math.sqrt(vx * vx + vy * vy)
        if vb * s > self.v_lin:
            s, why = self.v_lin / vb, "base_speed"
        if abs(wz) * s > self.w_base:
            s, why = self.w_base / abs(wz), "base_yaw_rate"
        peak = self._wheel_peak(vx, vy, wz)
        if peak * s > self.wheel:
            s, why = self.wheel / peak, "wheel_speed"
        v = (J @ qdot).tolist()
        vl = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
        if vl * s > self.ee_lin:
            s, why = self.ee_lin / vl, "ee_speed"
        va = math.sqrt(v[3] * v[3] + v[4] * v[4] + v[5] * v[5])
        if va * s > self.ee_ang:
            s, why = self.ee_ang / va, "ee_angular_speed"
        if M_a is not None and M_b is not None and self.energy < _INF:
            qa = qdot[:6]
            e = 0.5 * float(qa @ M_a @ qa) + 0.5 * (M_b[0] * vx * vx + M_b[1] * vy * vy
                                                    + M_b[2] * wz * wz)
            if e * s * s > self.energy:
                s, why = math.sqrt(self.energy / e), "energy"
        return (s, why) if math.isfinite(s) else (0.0, "")

    def _joint_scale(self, qd: list[float], q_a: Vec) -> tuple[float, str]:
        """Largest s in [0, 1] with s*qd[:6] within the joint speed and position caps."""
        up, down = self.joint_caps(q_a.tolist())
        s, why = 1.0, ""
        for i in range(6):
            v = qd[i]
            if v > 0.0:
                cap = up[i]
            elif v < 0.0:
                cap, v = down[i], -v
            else:
                continue
            if cap < s * v:
                s = cap / v
                why = "joint_speed" if cap >= self._vj[i] else "joint_position"
        return s, why

    def _wheel_peak(self, vx: float, vy: float, wz: float) -> float:
        """max |wheel speed| [rad/s] for a base twist (mecanum matrix rows)."""
        peak = 0.0
        for row in self._W:
            w = abs(row[0] * vx + row[1] * vy + row[2] * wz)
            peak = max(peak, w)
        return peak

    def acceleration_scale(self, delta: Vec, dt: float) -> float:
        """Largest s in [0, 1] with s*delta (9,) within the acceleration limits over dt [s]."""
        d = delta.tolist()
        s = 1.0
        for i in range(6):
            m = abs(d[i])
            cap = self._aj[i] * dt
            if m * s > cap:
                s = cap / m
        dl = math.sqrt(d[6] * d[6] + d[7] * d[7])
        if dl * s > self.a_lin * dt:
            s = self.a_lin * dt / dl
        dw = abs(d[8])
        if dw * s > self.a_ang * dt:
            s = self.a_ang * dt / dw
        return s if math.isfinite(s) else 0.0

    def apply(self, qdot_d: Vec, qdot_prev: Vec, q: Vec, J: Vec, dt: float,
              M_a: Vec | None = None, M_b: Vec | None = None) -> Limited:
        """Limit ``qdot_d`` (9,) given the previous command (9,), ``q`` (9,), J (6, 9)
        and, for the energy cap, the arm's inertia M_a (6, 6) and the base's M_b (3,)."""
        if not (np.isfinite(qdot_d).all() and np.isfinite(qdot_prev).all()):
            return Limited(np.zeros(9), 0.0, 0.0, 0.0)
        q_a = q[:6]
        s_v, why = self.velocity_scale_why(qdot_d, q_a, J, M_a, M_b)
        qv = s_v * qdot_d
        delta = qv - qdot_prev
        s_a = self.acceleration_scale(delta, dt) if dt > 0.0 else 1.0
        if s_a >= 1.0:  # qv meets every velocity cap by construction
            return Limited(qv, s_v, s_a, 1.0, why)
        out = qdot_prev + s_a * delta
        s_f = self._joint_scale(out.tolist(), q_a)[0]
        if s_f < 1.0:
            out = s_f * out
        return Limited(out, s_v, s_a, s_f, why or "acceleration")
