"""What both base transports share: twist -> limited wheel speeds, wheel angles -> odometry.

Pure (no I/O, no clocks): the transports pass in timestamps.  The kinematics are the
ones of :mod:`mmctl.control.mecanum`; this module only adds the wheel-limit scaling of
a command and the integration of wheel displacements into a pose.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from mmctl.config.base import MecanumConfig
from mmctl.control.mecanum import odometry_matrix, wheel_matrix, wheel_scale
from mmctl.types import Odometry, Twist

Vec = NDArray[np.float64]


class WheelCommand:
    """Turns a base twist into four wheel speeds within the wheel speed limit.

    geom: the mecanum geometry; wheel_limit: max |wheel speed| [rad/s].
    """

    def __init__(self, geom: MecanumConfig, wheel_limit: float) -> None:
        self._w = wheel_matrix(geom)
        self._limit = float(wheel_limit)

    def __call__(self, vx: float, vy: float, wz: float) -> tuple[Vec, Twist]:
        """(wheel speeds (4,) [rad/s] FL FR BL BR, the twist they realise).

        Every wheel speed is scaled by the same factor so none exceeds the limit: the
        twist's direction is kept, its magnitude shrinks.  Raises ValueError on a
        non-finite input.
        """
        if not (math.isfinite(vx) and math.isfinite(vy) and math.isfinite(wz)):
            raise ValueError(f"non-finite twist ({vx}, {vy}, {wz})")
        wheels = self._w @ np.array((vx, vy, wz))
        s = wheel_scale(wheels, self._limit)
        if s < 1.0:
            wheels *= s
        return wheels, Twist(vx * s, vy * s, wz * s)


class OdometryIntegrator:
    """Integrates wheel angle increments into a planar pose (odometry frame).

    Each increment dθ (4,) [rad] maps to a base-frame displacement through the
    least-squares inverse P (``(dx, dy, dyaw) = P dθ``), rotated into the odometry
    frame with the mid-step yaw.  ``yaw`` is continuous (not wrapped to ±π).
    """

    def __init__(self, geom: MecanumConfig) -> None:
        self._p = odometry_matrix(geom)
        self.x = 0.0
        self.y = 0.0
        self.yaw = 0.0
        self.twist = (0.0, 0.0, 0.0)
        self.timestamp = 0.0

    def reset(self, timestamp: float) -> None:
        """Pose back to the origin; ``timestamp`` = monotonic time [s] of the reference."""
        self.x = self.y = self.yaw = 0.0
        self.twist = (0.0, 0.0, 0.0)
        self.timestamp = timestamp

    def update(self, dtheta: Vec, wheel_speeds: Vec, timestamp: float) -> None:
        """Add one increment: wheel angles dθ (4,) [rad], current wheel speeds (4,)
        [rad/s], monotonic time of the newest sample [s]."""
        dx, dy, dyaw = self._p @ dtheta
        mid = self.yaw + 0.5 * dyaw
        c, s = math.cos(mid), math.sin(mid)
        self.x += c * dx - s * dy
        self.y += s * dx + c * dy
        self.yaw += dyaw
        vx, vy, wz = self._p @ wheel_speeds
        self.twist = (float(vx), float(vy), float(wz))
        self.timestamp = timestamp

    def odometry(self) -> Odometry:
        """The current estimate."""
        vx, vy, wz = self.twist
        return Odometry(float(self.x), float(self.y), float(self.yaw), vx, vy, wz,
                        self.timestamp)


def wrap_delta(new: int, old: int, bits: int = 32) -> int:
    """``new - old`` for two readings of a ``bits``-bit two's-complement counter that
    may have wrapped between them (|true delta| < 2^(bits-1))."""
    span = 1 << bits
    half = span >> 1
    return (new - old + half) % span - half
