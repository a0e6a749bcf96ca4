"""Virtual walls (``walls:``): the handle's box in the base frame, the base's keep-in
area in the world frame.  Pure functions of the pose; no state.

A wall is a plane (a box face, a polygon edge) with an inward normal ``n`` and the
signed distance ``d`` of the guarded point inside it.  The speed *into* the wall
(``u = -n . v > 0``) is bounded, and only that component is reduced: motion along the
wall and away from it stays free.  The bound is the approach curve of a braking at
``a`` that ends in an exponential approach with time constant ``tau``:

    u <= b(d) = a tau (sqrt(1 + 2 d / (a tau^2)) - 1)        (0 for d <= 0)

b(d) ~ d / tau near the wall and ~ sqrt(2 a d) far from it; a point that follows it
decelerates at a (s - 1) / s < a (s the square root): always within the acceleration
limits, so the limits downstream never have to overshoot it.  ``tau`` is chosen so that
b(margin) is the speed cap ``v``: tau = (2 margin a - v^2) / (2 v a), at least
:data:`TAU_MIN` (a margin shorter than the braking distance v^2 / (2 a) from the cap:
the braking then starts farther out).  Pushed on, the point never reaches the wall (per
cycle it covers dt / tau of what is left).  A bound, not a scale: the admittance's
state stays at the bound instead of collapsing each cycle, so the approach is smooth and
pushing away is felt at once.

The bound limits a velocity, not a position: the IDK's tracking error (the arm's
curvature over a cycle while it slides along a wall) and the drives' lag carry a point
past the bound by fractions of a millimetre.  Past a wall by up to
:data:`RETURN_DEPTH` (5 mm) the bound is negative, d / tau: the point is brought back
at d / tau (at most 25 mm/s for the handle).  Farther out that return fades to zero at
twice the depth, and beyond (a start outside the area, odometry reset) the point may
only move back: the robot never moves by itself toward a wall far away.

    handle: v the end-effector speed cap, a = 80 % of the smallest joint acceleration
            limit at 1 m from the joint (3.2 m/s^2 by default)
    base:   v the base's speed cap, a = 80 % of its linear acceleration limit

Where they act (:class:`~mmctl.control.step.Controller`):

* on the admittance's velocity ``v_d`` (control frame = base axes at the handle),
  before the IDK, and that filtered velocity is the admittance's state: a person who
  pushes into a wall feels it as a wall (no wind-up; letting go, nothing moves);
* the base area also on the IDK's base velocity, before the limits (the IDK may move
  the base outward while the handle moves along the wall, e.g. the null-space return
  to ``q_des``): a guarantee for the heavy part, at the price of the handle's velocity
  deviating from ``v_d`` while it binds.

The handle's box is not re-checked after the IDK: relative to the base the handle
moves only by the admittance (braked above) and by the null-space return toward
``q_des``, whose tool point the controller checks is inside the box.
"""

from __future__ import annotations

import math

import numpy as np

from mmctl.config.control import WallsConfig
from mmctl.types import Vec

#: a wall that removed less than this [m/s] did not bind (rounding)
_BOUND = 1e-9


#: the share of an acceleration limit the braking toward a wall plans on (as the
#: joints' position braking, :class:`~mmctl.control.limits.Limits`)
BRAKE_SHARE = 0.8
#: [s] the shortest time constant of the final approach (25 cycles at 500 Hz)
TAU_MIN = 0.05
#: [m] how deep past a wall a point is brought back by itself (what the IDK's tracking
#: error and the drives' lag carry it past the bound: fractions of a millimetre)
RETURN_DEPTH = 0.005


def approach_constant(margin: float, speed: float, accel: float) -> float:
    """tau [s] such that the approach curve allows ``speed`` at ``margin`` (>= TAU_MIN)."""
    return max((2.0 * margin * accel - speed * speed) / (2.0 * speed * accel), TAU_MIN)


def approach_bound(d: float, accel: float, tau: float) -> float:
    """b(d) [m/s] (the module docstring); past the wall d / tau within
    :data:`RETURN_DEPTH`, back to 0 at twice that, 0 farther out."""
    if d <= 0.0:
        if d >= -RETURN_DEPTH:
            return d / tau
        return min(0.0, (-2.0 * RETURN_DEPTH - d) / tau)
    at = accel * tau
    return at * (math.sqrt(1.0 + 2.0 * d / (at * tau)) - 1.0)


class Walls:
    """The configured walls; :meth:`from_config` gives None when there are none.

    ee_speed [m/s] and ee_acceleration [m/s^2]: the handle's speed cap and braking;
    base_speed [m/s] and base_acceleration [m/s^2]: the base's limits."""

    def __init__(self, cfg: WallsConfig, ee_speed: float, ee_acceleration: float,
                 base_speed: float, base_acceleration: float) -> None:
        self.margin = cfg.margin
        self.ee_accel = BRAKE_SHARE * ee_acceleration
        self.ee_tau = approach_constant(cfg.margin, ee_speed, self.ee_accel)
        self.base_accel = BRAKE_SHARE * base_acceleration
        self.base_tau = approach_constant(cfg.margin, base_speed, self.base_accel)
        box = cfg.ee_box
        self.box_lo = None if box is None else np.array(box[0], dtype=float)
        self.box_hi = None if box is None else np.array(box[1], dtype=float)
        self.normals: Vec | None = None  # (k, 2) inward unit normals of the area's edges
        self.offsets: Vec | None = None  # (k,): d = n . p - offset
        self._sharp = False  # a corner sharper than 90 deg (adjacent normals apart > 90)
        if cfg.base_area:
            pts = np.array(cfg.base_area, dtype=float)
            edges = np.roll(pts, -1, axis=0) - pts
            ccw = float(np.sum(pts[:, 0] * np.roll(pts[:, 1], -1)
                               - np.roll(pts[:, 0], -1) * pts[:, 1])) > 0.0
            normals = np.column_stack((-edges[:, 1], edges[:, 0]))  # left of each edge
            if not ccw:
                normals = -normals
            normals /= np.linalg.norm(normals, axis=1)[:, None]
            self.normals = normals
            self.offsets = np.einsum("ij,ij->i", normals, pts)
            self._sharp = bool(np.min(np.einsum("ij,ij->i", normals,
                                                np.roll(normals, -1, axis=0))) < 0.0)

    @classmethod
    def from_config(cls, cfg: WallsConfig, ee_speed: float, ee_acceleration: float,
                    base_speed: float, base_acceleration: float) -> Walls | None:
        if cfg.ee_box is None and not cfg.base_area:
            return None
        return cls(cfg, ee_speed, ee_acceleration, base_speed, base_acceleration)

    def base_bound(self, d: float) -> float:
        """[m/s] the base's largest speed toward an edge ``d`` [m] away."""
        return approach_bound(d, self.base_accel, self.base_tau)

    def ee_bound(self, d: float) -> float:
        """[m/s] the handle's largest speed toward a face of its box ``d`` [m] away."""
        return approach_bound(d, self.ee_accel, self.ee_tau)

    # --- the handle's box ------------------------------------------------------
    def box_distances(self, p_base: Vec) -> Vec:
        """(6,) distances [m] of the tool point (base frame) inside the box's faces
        x_min, y_min, z_min, x_max, y_max, z_max (negative: outside); empty: no box."""
        if self.box_lo is None or self.box_hi is None:
            return np.zeros(0)
        return np.concatenate((p_base - self.box_lo, self.box_hi - p_base))

    def filter_box(self, v: Vec, p_base: Vec) -> tuple[Vec, bool]:
        """``v`` (6,) control frame with its linear velocity into a face of the box
        bounded; (the new twist, whether a face bound it)."""
        lo, hi = self.box_lo, self.box_hi
        if lo is None or hi is None:
            return v, False
        out = v
        for i in range(3):
            vi = float(v[i])
            b_lo = self.ee_bound(float(p_base[i] - lo[i]))  # speed allowed toward -e_i
            b_hi = self.ee_bound(float(hi[i] - p_base[i]))
            w = min(max(vi, -b_lo), b_hi)
            if w != vi:
                if out is v:
                    out = v.copy()
                out[i] = w
        return out, out is not v and bool(np.any(np.abs(out - v) > _BOUND))

    # --- the base's area ---------------------------------------------------------
    def area_distances(self, x: float, y: float) -> Vec:
        """(k,) distances [m] of the base's centre inside the area's edges (negative:
        outside); empty: no area."""
        if self.normals is None or self.offsets is None:
            return np.zeros(0)
        d: Vec = self.normals @ np.array((x, y)) - self.offsets
        return d

    def filter_area(self, vx: float, vy: float, x: float, y: float) -> tuple[float, float, bool]:
        """A world-frame planar velocity (vx, vy) of the base at (x, y) with its speed
        out through each edge bounded (:meth:`base_bound`; twice over the edges when a
        corner is sharper than 90 deg, so that one edge cannot add back what its
        neighbour removed); (vx, vy, bound)."""
        if self.normals is None or self.offsets is None:
            return vx, vy, False
        bound = False
        d = self.area_distances(x, y)
        for _ in range(2):
            for (nx, ny), dj in zip(self.normals, d):
                u = -(nx * vx + ny * vy)  # outward speed through this edge
                cut = u - self.base_bound(float(dj))
                if cut > 0.0:
                    vx += cut * nx
                    vy += cut * ny
                    bound = bound or cut > _BOUND
            if not self._sharp:
                break  # no corner sharper than 90 deg: one pass is exact
        return vx, vy, bound

    def _bound_base_frame(self, vx: float, vy: float, q: Vec) -> tuple[float, float, bool]:
        """:meth:`filter_area` for a velocity given in the frame of the base at ``q``."""
        c, s = math.cos(q[8]), math.sin(q[8])
        wx, wy, bound = self.filter_area(c * vx - s * vy, s * vx + c * vy,
                                         float(q[6]), float(q[7]))
        return c * wx + s * wy, -s * wx + c * wy, bound

    def filter_twist_area(self, v: Vec, q: Vec) -> tuple[Vec, bool]:
        """The admittance's twist ``v`` (6,) (base axes) with its world-horizontal
        velocity out of the area bounded by the *base's* distances (the base
        follows the handle in the strategies that move it)."""
        if self.normals is None:
            return v, False
        vx, vy, bound = self._bound_base_frame(float(v[0]), float(v[1]), q)
        if not bound:
            return v, False
        out = v.copy()
        out[0], out[1] = vx, vy
        return out, True

    def clamp_base(self, qdot: Vec, q: Vec) -> tuple[Vec, bool]:
        """The IDK's command ``qdot`` (9,) with the base's velocity (base frame) out of
        the area bounded (the arm's part and the yaw rate kept)."""
        if self.normals is None:
            return qdot, False
        vx, vy, bound = self._bound_base_frame(float(qdot[6]), float(qdot[7]), q)
        if not bound:
            return qdot, False
        out = qdot.copy()
        out[6], out[7] = vx, vy
        return out, True
