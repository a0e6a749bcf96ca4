"""The whole control chain as one cycle: device readings in, commands out.

:class:`CycleChain` holds the chain's fixed parts, built once from a configuration:
:class:`~mmctl.control.wrench.WrenchProcessor` (tare, gravity compensation, dead band,
low-pass, frame, staleness and limit checks) and :class:`~mmctl.control.step.Controller`
(admittance, IDK strategy, limits, energy).  :meth:`CycleChain.cycle` maps
``(state, readings, now)`` to ``(state, result)``: no I/O, no clock, no logging, no state
kept between calls; faults come back as values (:attr:`CycleResult.fault`).  The daemon's
loop calls it through :class:`~mmctl.runtime.core.ControlCore`; tests call it with
scripted readings and a scripted clock.

While the robot is not armed (``readings.active`` false) the wrench is still processed
(so a tare progresses and stale/limit conditions are seen) but the controller does not
run: its state is held at rest, so arming never starts with a leftover admittance
velocity.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, NamedTuple

import numpy as np

from mmctl.config import Config
from mmctl.control.energy import Energy, kinetic_energy
from mmctl.control.step import Controller, ControllerState, StepInputs, StepOutputs
from mmctl.control.wrench import WrenchProcessor, WrenchState
from mmctl.errors import FaultCause
from mmctl.model.robot import RobotModel, tool_in_sensor
from mmctl.types import ArmState, Odometry, Vec, Wrench

_Z3 = np.zeros(3)
_Z6 = np.zeros(6)
_Z9 = np.zeros(9)
_ZERO_E = Energy(0.0, 0.0, 0.0)


class CycleResult(NamedTuple):
    """One cycle's numbers (SI units).

    q, qd: (9,) measured configuration / velocities (arm, then base x, y, yaw /
    vx, vy, wz); f_h: (6,) processed human wrench, control frame [N, N m];
    v_d: (6,) admittance twist; qd_cmd: (9,) command; qd_arm: (6,) speedJ [rad/s];
    twist: (3,) base command (vx, vy [m/s], wz [rad/s]), times the arm's speed
    scaling; p, p_des: (3,) tool position
    and FK(q_des) in the world [m]; energy: E_K from the measured velocities [J] (also
    when the controller did not run: a robot coasting to rest has energy);
    fault: SPEC §5 cause found by the pure chain (None = fine); fault_details: for the
    fault event; taring: a tare is running; out: the controller's outputs (None when
    it did not run); v: (6,) the measured end-effector twist J(q) q̇ in the control frame
    [m/s, rad/s] (zero at rest).
    """

    q: Vec
    qd: Vec
    f_h: Vec
    v_d: Vec
    qd_cmd: Vec
    qd_arm: Vec
    twist: Vec
    p: Vec
    p_des: Vec
    energy: Energy
    fault: FaultCause | None
    fault_details: dict[str, Any]
    taring: bool
    out: StepOutputs | None
    v: Vec = _Z6
    raw: Wrench | None = None
    """The sensor reading this cycle used, raw (sensor frame; the ROS 2 bridge's
    ``mmctl/wrench/raw``): the reading itself, so the cycle copies nothing."""


class CycleState(NamedTuple):
    """What one cycle hands to the next: the controller's and the wrench pipeline's."""

    controller: ControllerState
    wrench: WrenchState


class Readings(NamedTuple):
    """One cycle's inputs: the devices' readings, the period ``dt`` [s], whether the
    robot is armed (``active``: the controller runs and commands motion) and whether the
    enabling switch is held (``held``; False: the armed robot comes to rest and stays,
    see :class:`~mmctl.control.step.StepInputs`)."""

    arm: ArmState
    wrench: Wrench
    odom: Odometry
    dt: float
    active: bool
    held: bool = True



def _pose(q: Vec) -> list[float]:
    """The arm's part of ``q`` for a fault's details (where a singular pose was met)."""
    return [round(float(x), 4) for x in q[:6]]

class CycleChain:
    """The control chain's fixed parts (see the module docstring).

    cfg: the configuration; model: the robot model (built from ``cfg.robot`` if None).
    """

    def __init__(self, cfg: Config, model: RobotModel | None = None):
        self.cfg = cfg
        self.dt = 1.0 / cfg.loop.rate_hz
        self.model = model if model is not None else RobotModel(cfg.robot)
        self.controller = Controller(cfg, self.model)
        # the handle point in the sensor's own axes (robot.sensor_rotation)
        self.wrench = WrenchProcessor(cfg.sensor.wrench, self.dt, tool_in_sensor(cfg.robot))
        self.max_condition = cfg.safety.max_condition

    def initial_state(self) -> CycleState:
        """At rest, in ``idk.strategy``, no tare running."""
        return CycleState(self.controller.initial_state(), self.wrench.initial_state())

    def at_rest(self, state: CycleState) -> CycleState:
        """The controller at rest in its current mode, switch sub-mode and limits
        profile (on enable)."""
        ctl = state.controller
        rest = self.controller.set_switch(self.controller.initial_state(ctl.mode), ctl.switch)
        return state._replace(controller=dataclasses.replace(rest, reduced=ctl.reduced))

    def cycle(self, state: CycleState, r: Readings, now: float) -> tuple[CycleState, CycleResult]:
        """One cycle: ``now`` is the time [s] on the clock of the readings' timestamps
        (``time.monotonic`` on the robot); staleness is judged against it."""
        state, result = self._cycle(state, r, now)
        return state, result._replace(raw=r.wrench)

    def _cycle(self, state: CycleState, r: Readings, now: float
               ) -> tuple[CycleState, CycleResult]:
        q = np.empty(9)
        q[:6] = r.arm.q
        q[6], q[7], q[8] = r.odom.x, r.odom.y, r.odom.yaw
        qd = np.empty(9)
        qd[:6] = r.arm.qd
        qd[6], qd[7], qd[8] = r.odom.vx, r.odom.vy, r.odom.wz
        if not math.isfinite(float(q @ q + qd @ qd)):
            return self._idle(state, q, qd, _Z6, FaultCause.NON_FINITE,
                              {"where": "measured q/qd"})
        scaling = r.arm.speed_scaling
        if not math.isfinite(scaling):
            return self._idle(state, q, qd, _Z6, FaultCause.NON_FINITE,
                              {"where": "the arm's speed scaling"})
        r_sensor = self.model.fk_base(q, "sensor").rotation
        wstate, w = self.wrench.step(state.wrench, r.wrench, r_sensor, now)
        state = state._replace(wrench=wstate)
        if w.fault is not None:
            return self._idle(state, q, qd, w.f_h, w.fault, w.details)
        if not r.active or w.taring:
            cond = self.condition(q)
            if cond > self.max_condition:  # so enabling here is refused
                return self._idle(state, q, qd, w.f_h, FaultCause.SINGULAR,
                                  {"condition": cond, "q_arm": _pose(q), "qd_arm": _pose(qd)})
            body = self.controller.body
            inside = body.inside(q[:6]) if body is not None else None
            if inside is not None:  # so enabling here is refused too
                return self._idle(state, q, qd, w.f_h, FaultCause.SELF_COLLISION,
                                  {"pair": "-".join(inside[0]),
                                   "distance_m": round(inside[1], 4), "q_arm": _pose(q)})
            return self._idle(state, q, qd, w.f_h, None, {}, taring=w.taring)
        ctl, out = self.controller.step(state.controller,
                                        StepInputs(w.f_h, q, qd, r.dt, not r.held))
        state = state._replace(controller=ctl)
        if out.fault is not None:
            details: dict[str, Any] = {"condition": out.condition, "q_arm": _pose(q),
                                       "qd_arm": _pose(qd)}
            if out.fault is FaultCause.SELF_COLLISION and out.body is not None:
                details = {"pair": "-".join(out.body[0]),
                           "distance_m": round(out.body[1], 4), **details}
            return self._idle(state, q, qd, w.f_h, out.fault, details)
        # the controller executes speedJ at `scaling` of its speeds (speed slider, reduced
        # mode): the base goes as slowly, so the whole body moves as the IDK solved it
        twist = out.base_twist if scaling >= 1.0 else max(scaling, 0.0) * out.base_twist
        return state, CycleResult(q, qd, w.f_h, out.v_d, out.qdot, out.qdot_arm,
                                  twist, out.p, out.p_des, out.energy, None, {},
                                  False, out, out.v)

    def condition(self, q: Vec) -> float:
        """Condition number of J J^T at ``q`` (the controller's singularity measure)."""
        return self.model.condition(q)

    def _idle(self, state: CycleState, q: Vec, qd: Vec, f_h: Vec, fault: FaultCause | None,
              details: dict[str, Any], taring: bool = False
              ) -> tuple[CycleState, CycleResult]:
        """Not commanding: controller held at rest; positions for status/telemetry."""
        if state.controller.cycle or state.controller.v.any():
            state = self.at_rest(state)
        v, energy = _Z6, _ZERO_E
        if math.isfinite(float(q @ q)):
            p = self.model.position(q)
            p_des = self.controller.p_des(q)
            if qd.any() and math.isfinite(float(qd @ qd)):  # moving: what it measures
                kin = self.model.update(q)
                v = kin.J @ qd
                energy = kinetic_energy(kin.M_a, kin.M_b, qd)
        else:
            p = p_des = _Z3
        return state, CycleResult(q, qd, f_h, _Z6, _Z9, _Z6, _Z3, p, p_des, energy, fault,
                                  dict(details), taring, None, v)
