"""What the wrist sensor measures while a person pushes the handle.

The person's force acts at the handle (the tool frame's origin); the sensor, nearer the
flange, measures it in its own frame (``robot.sensor_offset``, axes turned by
``robot.sensor_rotation``) together with its moment about the sensor's origin, plus the
handle's weight (mass ``sim.handle_mass`` at ``sim.handle_com``, by default the daemon's
own ``sensor.wrench.handle_mass`` / ``handle_com``, so gravity compensation has
something to do) and a constant bias ``sim.sensor_bias`` (so the tare has something to
do).  A simulated handle that differs from the daemon's model is what `mmctl calibrate
tool` finds.  The simulated robot's sensors (:mod:`mmctl.sim.world`) and the study
(:mod:`mmctl.study.runner`) both feed the control chain this reading, so the study runs
the robot's whole wrench pipeline.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from mmctl.config import Config
from mmctl.control.wrench import G0
from mmctl.model.planar import world_to_base
from mmctl.model.robot import tool_in_sensor
from mmctl.types import Vec


def _cross(a: Vec, b: Vec) -> Vec:
    """a x b for 3-vectors (np.cross costs ~20 us of bookkeeping)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
                     a[0] * b[1] - a[1] * b[0]])


class HandleSensor:
    """The sensor's reading for a force at the handle (see the module docstring).

    cfg: the configuration (``robot.tool_offset``/``sensor_offset``/``sensor_rotation``:
    where the force acts relative to the sensor; ``sim.handle_mass``/``handle_com``, else
    ``sensor.wrench``'s: the handle's mass and centre of mass; ``sim.sensor_bias``);
    bias: (6,) the sensor's constant offset [N, N m], instead of ``sim.sensor_bias``.
    """

    def __init__(self, cfg: Config, bias: ArrayLike | None = None) -> None:
        self.lever = tool_in_sensor(cfg.robot)
        w, sim = cfg.sensor.wrench, cfg.sim
        self.mass = float(w.handle_mass if sim.handle_mass is None else sim.handle_mass)
        self.com = np.asarray(w.handle_com if sim.handle_com is None else sim.handle_com,
                              dtype=float)
        self.bias = np.asarray(sim.sensor_bias if bias is None else bias, dtype=float)
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
