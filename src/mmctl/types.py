"""Plain values passed between layers (SI units, radians, monotonic seconds)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

Vec = NDArray[np.float64]


class Wrench(NamedTuple):
    """A force/torque sample in the sensor frame.

    force: (3,) [N]; torque: (3,) [N m]; timestamp: time.monotonic() of reception [s];
    sequence: the transport's sample counter; status: the device status word (0 = ok).
    """

    force: Vec
    torque: Vec
    timestamp: float
    sequence: int
    status: int = 0

    def as_array(self) -> Vec:
        """The 6-vector (fx, fy, fz, tx, ty, tz)."""
        return np.concatenate((self.force, self.torque))


class Twist(NamedTuple):
    """A planar base twist in the base frame: vx, vy [m/s], wz [rad/s]."""

    vx: float
    vy: float
    wz: float


class Odometry(NamedTuple):
    """Base pose in the odometry frame (x, y [m], yaw [rad]), its twist in the base frame,
    and the monotonic time [s] of the newest encoder sample it uses."""

    x: float
    y: float
    yaw: float
    vx: float
    vy: float
    wz: float
    timestamp: float


class ArmState(NamedTuple):
    """One RTDE sample of the UR10e.

    q, qd: (6,) [rad], [rad/s]; controller_time: the controller's timestamp [s];
    runtime_state: RTDE runtime state (2 = PLAYING); safety_bits: RTDE safety status bits;
    speed_scaling: the fraction of a commanded speed the controller executes (its
    trajectory limiter's ``speed_scaling`` times the speed slider's
    ``target_speed_fraction``: ur_rtde's getSpeedScalingCombined), 0..1.
    """

    q: Vec
    qd: Vec
    controller_time: float
    runtime_state: int
    safety_bits: int
    speed_scaling: float = 1.0
