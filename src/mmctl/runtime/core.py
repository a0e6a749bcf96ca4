"""The control chain as the daemon calls it: device readings in, commands out.

:class:`ControlCore` owns the pure pieces — :class:`~mmctl.control.wrench.WrenchProcessor`
(tare, gravity compensation, dead band, low-pass, mask, stale/limit checks) and
:class:`~mmctl.control.step.Controller` (admittance, IDK strategy, limits, energy) —
and their states, and turns one cycle's ``ArmState``/``Wrench``/``Odometry`` into a
:class:`CycleResult`.  No I/O and no logging: faults come back as values.

While the robot is not armed (``active=False``) the wrench is still processed (so a
tare progresses and stale/limit conditions are seen) but the controller does not run:
its state is held at rest, so arming never starts with a leftover admittance velocity.
"""

from __future__ import annotations

import math
import time
from typing import Any, NamedTuple

import numpy as np

from mmctl.config import Config
from mmctl.control.energy import Energy
from mmctl.control.step import Controller, ControllerState, StepInputs, StepOutputs
from mmctl.control.wrench import WrenchProcessor
from mmctl.errors import FaultCause
from mmctl.model.robot import RobotModel
from mmctl.telemetry import ring as tr
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
    twist: (3,) base command (vx, vy [m/s], wz [rad/s]); p, p_des: (3,) tool position
    and FK(q_des) in the world [m]; energy: E_K from measured velocities [J];
    fault: SPEC §5 cause found by the pure chain (None = fine); fault_details: for the
    fault event; taring: a tare is running; out: the controller's outputs (None when
    it did not run).
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


class ControlCore:
    """Wrench processing + controller with their states (loop thread only)."""

    def __init__(self, cfg: Config, model: RobotModel | None = None):
        self.cfg = cfg
        self.dt = 1.0 / cfg.loop.rate_hz
        self.model = model if model is not None else RobotModel(cfg.robot)
        self.controller = Controller(cfg, self.model)
        control_point = np.subtract(cfg.robot.tool_offset, cfg.robot.sensor_offset)
        self.wrench = WrenchProcessor(cfg.sensor.wrench, self.dt, control_point)
        self.state: ControllerState = self.controller.initial_state()
        self.wstate = self.wrench.initial_state()

    # -- operator commands (loop thread) ------------------------------------------------
    @property
    def mode(self) -> str:
        return self.state.mode.value

    @property
    def switch(self) -> str:
        return self.state.switch.value

    @property
    def taring(self) -> bool:
        return self.wstate.tare_left > 0

    def set_mode(self, mode: str) -> None:
        """Another IDK strategy; the controller cross-fades (no velocity jump)."""
        self.state = self.controller.set_mode(self.state, mode)

    def set_switch(self, which: str) -> None:
        """manipulation / locomotion sub-mode of the switch strategy (cross-faded)."""
        self.state = self.controller.set_switch(self.state, which)

    def toggle_switch(self) -> None:
        self.state = self.controller.toggle_switch(self.state)

    def start_tare(self) -> None:
        """Average the next ``tare_samples`` fresh samples into the sensor bias."""
        self.wstate = self.wrench.start_tare(self.wstate)

    def reset(self) -> None:
        """Controller at rest in the current mode and switch sub-mode (on enable)."""
        st = self.controller.initial_state(self.state.mode)
        self.state = self.controller.set_switch(st, self.state.switch)

    # -- the cycle ----------------------------------------------------------------------
    def step(self, arm: ArmState, wrench: Wrench, odom: Odometry, dt: float,
             active: bool, now: float | None = None) -> CycleResult:
        """One cycle from the device readings; ``active``: the robot is armed."""
        q = np.empty(9)
        q[:6] = arm.q
        q[6], q[7], q[8] = odom.x, odom.y, odom.yaw
        qd = np.empty(9)
        qd[:6] = arm.qd
        qd[6], qd[7], qd[8] = odom.vx, odom.vy, odom.wz
        if not math.isfinite(float(q @ q + qd @ qd)):
            return self._idle(q, qd, _Z6, FaultCause.NON_FINITE, {"where": "measured q/qd"})
        r_sensor = self.model.fk_base(q, "sensor").rotation
        t_now = time.monotonic() if now is None else now
        self.wstate, w = self.wrench.step(self.wstate, wrench, r_sensor, t_now)
        if w.fault is not None:
            return self._idle(q, qd, w.f_h, w.fault, w.details)
        if not active or w.taring:
            cond = self.condition(q)
            if cond > self.cfg.safety.max_condition:  # so enabling here is refused
                return self._idle(q, qd, w.f_h, FaultCause.SINGULAR, {"condition": cond})
            return self._idle(q, qd, w.f_h, None, {}, taring=w.taring)
        self.state, out = self.controller.step(self.state, StepInputs(w.f_h, q, qd, dt))
        if out.fault is not None:
            return self._idle(q, qd, w.f_h, out.fault, {"condition": out.condition})
        return CycleResult(q, qd, w.f_h, out.v_d, out.qdot, out.qdot_arm, out.base_twist,
                           out.p, out.p_des, out.energy, None, {}, False, out)

    def condition(self, q: Vec) -> float:
        """Condition number of J J^T at ``q`` (the controller's singularity measure)."""
        jac = self.model.jacobian(q)
        w = np.linalg.eigvalsh(jac @ jac.T)
        return float(w[-1] / w[0]) if w[0] > 0.0 else math.inf

    def _idle(self, q: Vec, qd: Vec, f_h: Vec, fault: FaultCause | None,
              details: dict[str, Any], taring: bool = False) -> CycleResult:
        """Not commanding: controller held at rest; positions for status/telemetry."""
        if self.state.cycle or self.state.v.any():
            self.reset()
        if math.isfinite(float(q @ q)):
            p = self.model.position(q)
            p_des = self.controller.p_des(q)
        else:
            p = p_des = _Z3
        return CycleResult(q, qd, f_h, _Z6, _Z9, _Z6, _Z3, p, p_des, _ZERO_E, fault,
                           dict(details), taring, None)

    # -- telemetry ----------------------------------------------------------------------
    def fill_row(self, r: CycleResult, cycle: int, t: float, safety: str,
                 prev: tuple[float, ...], row: Any) -> None:
        """Write this cycle and the previous cycle's timing ``prev`` (latency, compute,
        slack, missed [ns]) into a telemetry row (:mod:`mmctl.telemetry.ring` layout) in
        place: the loop's telemetry hot path, one numpy call.

        The row holds what the cycle has at hand (world-frame positions; the consumer
        derives the base frame and the wheel speeds); ``v`` is the step's own J(q) q̇ (no
        second Jacobian on the loop), or J(q) q̇ from the measured velocities when the
        controller did not run (0 without a Jacobian when they are all 0).
        """
        q = r.q
        mode = self.mode if self.mode != "switch" else f"switch/{self.switch}"
        if r.out is not None:
            v = r.out.v
        elif not r.qd.any():  # standing still (disarmed, stopped): J(q) 0 is 0, no Jacobian
            v = _Z6
        else:
            jac = self.model.jacobian(q) if math.isfinite(float(q @ q)) else np.zeros((6, 9))
            v = jac @ r.qd
        e = r.energy
        np.concatenate(((cycle, t, tr.mode_code(mode), tr.safety_code(safety), *prev), q,
                        r.f_h, r.v_d, v, r.qd_cmd, (e.total, e.arm, e.base), r.p, r.p_des),
                       out=row)

