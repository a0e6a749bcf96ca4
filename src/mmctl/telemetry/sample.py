"""The per-cycle telemetry value the loop thread hands to the publisher.

One :class:`TelemetrySample` per control cycle.  Building it costs one tuple: the
arrays are the ones the cycle produced (the producer must not mutate them afterwards;
the control step returns fresh arrays every cycle).  Everything the viewer draws and
everything the trial metrics (paper eq. 14-16) need is in it; loop timings are not,
the publisher reads them from the loop's :class:`~mmctl.runtime.timing.TimingRing`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

Vec = NDArray[np.float64]
_NAN6 = np.full(6, math.nan)
_NAN6.setflags(write=False)


class TelemetrySample(NamedTuple):
    """What one control cycle produced (SI units, radians).

    cycle: loop cycle index k (the ``cycle`` timeline);
    t: the cycle's deadline since the loop's origin [s] (the ``time`` timeline);
    q_a: (6,) actual arm joint positions [rad];
    base_pose: (3,) odometry pose x, y [m], yaw [rad];
    f_h: (6,) human wrench in the control frame [N, N m];
    v_d: (6,) desired end-effector twist, the admittance output [m/s, rad/s];
    v: (6,) actual end-effector twist ``J(q) q̇`` [m/s, rad/s];
    qd_cmd: (9,) commanded velocities: arm (6) [rad/s], base vx, vy [m/s], wz [rad/s]
    (the wheel speeds follow from the base part and the wheel geometry);
    e_total, e_arm, e_base: kinetic energy E_K and its arm / base parts [J];
    p: (3,) end-effector position ``FK(q)`` in the world (odometry) frame [m];
    p_des: (3,) preferred position ``FK(q_des)``, base at its pose, in the same frame [m]
    (the publisher plots both in the mobile base frame);
    mode: the active IDK strategy / switch sub-mode (its name);
    safety: the safety state (its name);
    limit: the limit that bound the command (:data:`~mmctl.control.limits.LIMIT_NAMES`,
    "" none); limit_scale: the scale the limits applied to the IDK's command (1: free);
    nearest: the distance of the robot's two nearest parts [m] (the self-collision
    check's; NaN when it did not run); qd_a: (6,) measured arm joint velocities [rad/s]
    (NaN: not known); f_raw: (6,) the sensor's raw wrench, sensor frame [N, N m].
    """

    cycle: int
    t: float
    q_a: Vec
    base_pose: Vec
    f_h: Vec
    v_d: Vec
    v: Vec
    qd_cmd: Vec
    e_total: float
    e_arm: float
    e_base: float
    p: Vec
    p_des: Vec
    mode: str
    safety: str
    limit: str = ""
    limit_scale: float = 1.0
    nearest: float = math.nan
    qd_a: Vec = _NAN6
    f_raw: Vec = _NAN6



def zero_sample(cycle: int = 0, t: float = 0.0) -> TelemetrySample:
    """A sample with every quantity zero (robot at rest, arm at zero joints)."""
    z3, z6 = np.zeros(3), np.zeros(6)
    return TelemetrySample(cycle, t, z6, z3, z6, z6, z6, np.zeros(9),
                           0.0, 0.0, 0.0, z3, z3, "idle", "disarmed")
