"""The arm's joints: six joints that follow speedJ under an acceleration limit.

URScript's ``speedj(qd, a)`` accelerates the joints towards ``qd`` with ``a`` the
acceleration of the *leading* axis; the other joints are scaled so that all of them
reach their target together (the velocity change keeps its direction).  ``stopj(a)``
is the same towards zero.  Positions integrate the velocity with the trapezoidal rule.
Pure Python (six joints): cheaper than numpy at this size, and the fake's process
starts without importing numpy.  Part of the simulated robot's one plant
(:mod:`mmctl.sim.plant`): the fake UR controller runs it in real time, the study in
simulated time.
"""

from __future__ import annotations

import math
from enum import Enum

TWO_PI = 2.0 * math.pi
MIN_ACCELERATION = 1e-3
"""[rad/s^2] smallest acceleration honoured (speedJ with a = 0 would never move)."""


class Motion(str, Enum):
    """What the joints are doing."""

    IDLE = "idle"
    SPEED = "speed"  # following a speedJ target
    STOPPING = "stopping"  # decelerating to rest


class JointPlant:
    """Joint positions q [rad] and velocities qd [rad/s] of a UR arm.

    q_min, q_max: joint position limits [rad]; reaching one stops the joint there and
    sets :attr:`limit_hit` (the controller turns that into a protective stop).
    """

    def __init__(self, q: list[float], q_min: float = -TWO_PI, q_max: float = TWO_PI):
        if len(q) != 6:
            raise ValueError(f"q must have 6 joints, got {len(q)}")
        self.q = [float(x) for x in q]
        self.qd = [0.0] * 6
        self.qdd = [0.0] * 6
        self.target = [0.0] * 6
        self.acceleration = 1.0
        self.motion = Motion.IDLE
        self.q_min = q_min
        self.q_max = q_max
        self.limit_hit = False
        self.scale = 1.0
        """The controller's speed scaling (the pendant's speed slider, 0..1): a speedJ
        target is followed at ``scale`` times its speeds."""

    def speed(self, qd: list[float], acceleration: float) -> None:
        """Follow joint speeds ``qd`` [rad/s] with leading-axis acceleration [rad/s^2]."""
        self.target = [float(x) if math.isfinite(x) else 0.0 for x in qd]
        self.acceleration = max(float(acceleration), MIN_ACCELERATION) \
            if math.isfinite(acceleration) else MIN_ACCELERATION
        self.motion = Motion.SPEED

    def stop(self, deceleration: float) -> None:
        """Decelerate to rest with the leading axis at ``deceleration`` [rad/s^2]."""
        self.target = [0.0] * 6
        self.acceleration = max(float(deceleration), MIN_ACCELERATION) \
            if math.isfinite(deceleration) else MIN_ACCELERATION
        self.motion = Motion.STOPPING

    def set_q(self, q: list[float]) -> None:
        """Teleport to ``q`` [rad] at rest (a test or a simulation reset)."""
        self.q = [float(x) for x in q]
        self.qd = [0.0] * 6
        self.qdd = [0.0] * 6
        self.target = [0.0] * 6
        self.motion = Motion.IDLE
        self.limit_hit = False

    def step(self, dt: float) -> None:
        """Advance ``dt`` [s]."""
        qd = self.qd
        if self.motion is Motion.IDLE:
            self.qdd = [0.0] * 6
            return
        k = self.scale if self.motion is Motion.SPEED else 1.0
        dv = [k * t - v for t, v in zip(self.target, qd)]
        lead = max(abs(x) for x in dv)
        limit = self.acceleration * dt
        if lead > limit:
            scale = limit / lead
            dv = [x * scale for x in dv]
        new = [v + d for v, d in zip(qd, dv)]
        self.qdd = [d / dt for d in dv]
        q = [p + 0.5 * (a + b) * dt for p, a, b in zip(self.q, qd, new)]
        for i, p in enumerate(q):
            if p < self.q_min or p > self.q_max:
                q[i] = min(max(p, self.q_min), self.q_max)
                new[i] = 0.0
                self.limit_hit = True
        self.q = q
        self.qd = new
        if self.motion is Motion.STOPPING and lead <= limit:
            self.motion = Motion.IDLE
