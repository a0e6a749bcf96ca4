"""Mecanum-wheel kinematics of the RB-KAIROS+ (pure functions).

Wheel order FL, FR, BL, BR. With l = half_length + half_width and wheel radius r,
wheel speeds [rad/s] from the base twist (vx, vy [m/s], wz [rad/s], base frame)::

    FL = (vx - vy - l wz) / r      FR = (vx + vy + l wz) / r
    BL = (vx + vy - l wz) / r      BR = (vx - vy + l wz) / r

each multiplied by the wheel's mounting sign.  Odometry is the least-squares inverse.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from mmctl.config.base import MecanumConfig

Mat = NDArray[np.float64]


def wheel_matrix(geom: MecanumConfig) -> Mat:
    """The (4, 3) matrix W with wheel speeds [rad/s] = W @ (vx, vy, wz)."""
    ell = geom.half_length + geom.half_width
    w = np.array(
        [
            [1.0, -1.0, -ell],
            [1.0, 1.0, ell],
            [1.0, 1.0, -ell],
            [1.0, -1.0, ell],
        ]
    ) / geom.wheel_radius
    return np.asarray(geom.wheel_signs, dtype=float)[:, None] * w


def odometry_matrix(geom: MecanumConfig) -> Mat:
    """The (3, 4) least-squares inverse of :func:`wheel_matrix`: twist = P @ wheels."""
    return np.asarray(np.linalg.pinv(wheel_matrix(geom)), dtype=np.float64)


def twist_to_wheels(geom_or_w: MecanumConfig | Mat, twist: Mat) -> Mat:
    """Wheel speeds (4,) [rad/s] for a base twist (3,) (vx, vy [m/s], wz [rad/s])."""
    w = geom_or_w if isinstance(geom_or_w, np.ndarray) else wheel_matrix(geom_or_w)
    wheels: Mat = w @ np.asarray(twist, dtype=float)
    return wheels


def wheels_to_twist(geom_or_p: MecanumConfig | Mat, wheels: Mat) -> Mat:
    """Base twist (3,) from four wheel speeds [rad/s] (least squares)."""
    p = geom_or_p if isinstance(geom_or_p, np.ndarray) else odometry_matrix(geom_or_p)
    twist: Mat = p @ np.asarray(wheels, dtype=float)
    return twist


def wheel_scale(wheels: Mat, limit: float) -> float:
    """The factor in (0, 1] that brings every |wheel speed| within ``limit`` [rad/s].

    Multiplying the whole twist by it keeps the twist's direction.
    """
    # (plain floats: the peak numpy's max of |w| gives, at a fraction of its cost per
    # call; a NaN or inf anywhere: 0, as numpy's NaN-propagating max gave)
    mags = [abs(w) for w in np.asarray(wheels, dtype=float).tolist()]
    if not all(map(math.isfinite, mags)):
        return 0.0
    peak = max(mags, default=0.0)
    return 1.0 if peak <= limit else limit / peak
