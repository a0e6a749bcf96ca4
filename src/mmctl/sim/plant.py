"""The simulated robot's one plant: the arm's joints and the base's wheels.

One model of how the robot moves, used by everything that simulates it:

* the fake UR controller (:mod:`mmctl.sim.fake_ur`) runs
  :class:`~mmctl.sim.joints.JointPlant`: speedJ's leading-axis acceleration, stopj's
  deceleration, the joint limits;
* the fake CiA 402 drives (:mod:`mmctl.sim.fake_drives`) and the fake serial bridge run
  :class:`~mmctl.sim.wheels.WheelPlant`: each wheel ramps toward its velocity target at
  its drive's acceleration, the pose integrates the wheel increments;
* the study (:mod:`mmctl.study.runner`) runs :class:`Plant`: the two together in
  simulated time, commanded as the daemon commands the devices: speedJ with
  ``arm.speedj_acceleration``; the base twist turned into wheel speeds within
  ``limits.wheel_velocity`` by the base transports' own
  :class:`~mmctl.transports.base.kinematics.WheelCommand`, each wheel at the
  acceleration the CANopen transport writes to its drive (0x6083/0x6084:
  ``limits.base_linear_acceleration / mecanum.wheel_radius``), with the base's command
  latency, the drives' velocity loop and mecanum slip of the ``sim:`` section
  (:class:`~mmctl.sim.wheels.BaseDynamics`).

Two views of the base: :meth:`Plant.state` is where the robot actually is and how it
actually moves (what the person's hand and the world see: slip included);
:meth:`Plant.odometry` is what the wheel encoders say (what the controller sees, as the
daemon's odometry on the robot).  With no slip they are equal.

Coordinates: ``q = (q_1..q_6 [rad], x_b, y_b [m], yaw_b [rad])`` (base pose in the
world), ``q̇ = (q̇_1..q̇_6 [rad/s], v_x, v_y [m/s], ω_z [rad/s])`` (base twist in the
base frame): the controller's measured ``q``/``q̇``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from mmctl.config import Config
from mmctl.sim.joints import JointPlant
from mmctl.sim.wheels import BaseDynamics, WheelPlant
from mmctl.transports.base.kinematics import WheelCommand

Vec = NDArray[np.float64]


class PlantState(NamedTuple):
    """Actual whole-body configuration ``q`` (9,) and velocity ``qd`` (9,) (layout above)."""

    q: Vec
    qd: Vec


class BaseOdometry(NamedTuple):
    """What the wheel encoders say: ``pose`` (3,) (x, y [m], yaw [rad], world frame,
    integrated from the wheel increments) and ``twist`` (3,) (v_x, v_y [m/s], ω_z
    [rad/s], base frame, of the wheel speeds)."""

    pose: Vec
    twist: Vec


class Plant:
    """The arm's joints and the base's wheels in simulated time (see the module doc).

    cfg: the daemon's configuration (accelerations, limits, wheel geometry, the base's
    dynamics ``sim.base_*``); q0: (9,) the start configuration, at rest (odometry and
    world agree there); t0: the simulated clock's start [s].
    """

    def __init__(self, cfg: Config, q0: ArrayLike, t0: float = 0.0) -> None:
        q = np.array(q0, dtype=float)
        if q.shape != (9,):
            raise ValueError(f"q0 must have shape (9,), got {q.shape}")
        geom = cfg.base.mecanum
        self.arm = JointPlant([float(x) for x in q[:6]])
        self.arm_acceleration = float(cfg.arm.speedj_acceleration)
        self.wheels = WheelPlant(geom, cfg.limits.base_linear_acceleration / geom.wheel_radius,
                                 None, t0=t0, dynamics=BaseDynamics.from_config(cfg.sim))
        self.wheels.set_pose(float(q[6]), float(q[7]), float(q[8]))
        for i in range(4):
            self.wheels.track(i, t0)
        self._command = WheelCommand(geom, cfg.limits.wheel_velocity)
        self.t = t0
        self._state: PlantState | None = None  # state() until the plant moves

    def state(self) -> PlantState:
        """The actual ``q``, ``q̇`` now (the base where it is, slip included; read-only
        arrays, the same ones until the plant moves)."""
        if self._state is not None:
            return self._state
        q = np.empty(9)
        qd = np.empty(9)
        q[:6] = self.arm.q
        qd[:6] = self.arm.qd
        q[6:] = self.wheels.pose
        qd[6:] = self.wheels.twist()
        q.setflags(write=False)
        qd.setflags(write=False)
        self._state = PlantState(q, qd)
        return self._state

    def odometry(self) -> BaseOdometry:
        """The base as its wheel encoders report it now (no slip: equal to
        :meth:`state`'s base part)."""
        return BaseOdometry(self.wheels.odometry_pose.copy(), self.wheels.odometry_twist())

    def step(self, qd_arm: ArrayLike, base_twist: ArrayLike, dt: float) -> PlantState:
        """Send speedJ(``qd_arm`` (6,) [rad/s]) and the base twist (3,) (v_x, v_y [m/s],
        ω_z [rad/s], base frame), advance ``dt`` [s]; returns the new state."""
        if dt <= 0.0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        self._state = None
        self.arm.speed(np.asarray(qd_arm, dtype=float).tolist(), self.arm_acceleration)
        self.arm.step(dt)
        vx, vy, wz = np.asarray(base_twist, dtype=float).tolist()
        wheels, _twist = self._command(vx, vy, wz)
        self.wheels.command_all(wheels, self.t)
        self.t += dt
        self.wheels.advance(self.t)
        return self.state()
