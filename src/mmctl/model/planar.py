"""The base's planar pose: rotating vectors between the world and the base frame.

The base moves in the world's x-y plane with heading ``yaw`` [rad] (``q[8]``); its frame
is the world's turned by ``yaw`` about z.  Written out (no 3x3 products) so that the
hot paths and the simulation compute exactly the same numbers."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

Vec = NDArray[np.float64]


def rot_z(yaw: float) -> Vec:
    """(3, 3) rotation about z by ``yaw`` [rad]: base frame -> world frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def base_to_world(v: ArrayLike, yaw: float) -> Vec:
    """A base-frame vector (3,) in the world frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    a = np.asarray(v, dtype=float)
    return np.array([c * a[0] - s * a[1], s * a[0] + c * a[1], a[2]])


def world_to_base(v: ArrayLike, yaw: float) -> Vec:
    """A world-frame vector (3,) in the base frame."""
    c, s = math.cos(yaw), math.sin(yaw)
    a = np.asarray(v, dtype=float)
    return np.array([c * a[0] + s * a[1], -s * a[0] + c * a[1], a[2]])


def point_to_world(x: float, y: float, yaw: float, p: ArrayLike) -> Vec:
    """A point (3,) given in the frame of a base at (``x``, ``y``, ``yaw``), in the world."""
    c, s = math.cos(yaw), math.sin(yaw)
    a = np.asarray(p, dtype=float)
    return np.array([x + c * a[0] - s * a[1], y + s * a[0] + c * a[1], a[2]])
