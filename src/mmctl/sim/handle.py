"""What the wrist sensor measures while a person pushes the handle.

The person's force acts at the handle (the tool frame's origin); the sensor, nearer the
flange, measures it in its own frame together with its moment about the sensor's
origin, plus the handle's weight (mass ``sensor.wrench.handle_mass`` at
``handle_com``, so gravity compensation has something to do) and a constant bias (so
the tare has something to do).  The simulated robot's sensors (:mod:`mmctl.sim.world`)
and the study (:mod:`mmctl.study.runner`) both feed the control chain this reading,
so the study runs the robot's whole wrench pipeline.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from mmctl.config import Config
from mmctl.control.wrench import G0
from mmctl.model.planar import world_to_base
from mmctl.types import Vec

SENSOR_BIAS = np.array([1.2, -0.7, 2.5, 0.04, -0.03, 0.02])
"""A constant offset the simulated sensor adds (what a tare removes) [N, N m]."""


def _cross(a: Vec, b: Vec) -> Vec:
    """a x b for 3-vectors (np.cross costs ~20 us of bookkeeping)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


class HandleSensor:
    """The sensor's reading for a force at the handle (see the module docstring).

    cfg: the configuration (``robot.tool_offset``/``sensor_offset``: where the force
    acts relative to the sensor; ``sensor.wrench``: the handle's mass and centre of
    mass); bias: (6,) the sensor's constant offset [N, N m].
    """

    def __init__(self, cfg: Config, bias: ArrayLike = SENSOR_BIAS) -> None:
        self.lever = np.subtract(cfg.robot.tool_offset, cfg.robot.sensor_offset)
        w = cfg.sensor.wrench
        self.mass = float(w.handle_mass)
        self.com = np.asarray(w.handle_com, dtype=float)
        self.bias = np.asarray(bias, dtype=float)
        if self.bias.shape != (6,):
            raise ValueError(f"bias must have shape (6,), got {self.bias.shape}")

    def measure(self, force_world: ArrayLike, yaw: float, r_base_sensor: Vec) -> Vec:
        """(6,) force [N] and torque [N m] in the sensor frame for the person's force
        ``force_world`` (3,) [N] at the handle; ``yaw``: the base's heading [rad];
        ``r_base_sensor`` (3, 3): the sensor's orientation in the base frame."""
        f_s = r_base_sensor.T @ world_to_base(np.asarray(force_world, dtype=float), yaw)
        g_s = r_base_sensor.T @ np.array([0.0, 0.0, -self.mass * G0])
        out = np.empty(6)
        out[:3] = f_s + g_s
        out[3:] = _cross(self.lever, f_s) + _cross(self.com, g_s)
        measured: Vec = out + self.bias
        return measured
