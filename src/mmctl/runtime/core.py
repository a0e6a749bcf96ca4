"""The control chain as the daemon's loop calls it: :class:`ControlCore` keeps the
:class:`~mmctl.control.cycle.CycleState` between cycles, reads the clock, and carries
the operator's commands (mode, switch, tare, enable's reset) into that state; the
cycle itself is :meth:`mmctl.control.cycle.CycleChain.cycle`, pure."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from mmctl.config import Config
from mmctl.control.cycle import CycleChain, CycleResult, CycleState, Readings
from mmctl.control.params import get_value, with_value
from mmctl.control.step import Controller, ControllerState
from mmctl.control.wrench import WrenchState
from mmctl.model.robot import RobotModel
from mmctl.telemetry import ring as tr
from mmctl.types import ArmState, Odometry, Vec, Wrench

__all__ = ["ControlCore", "CycleResult"]

_Z6 = np.zeros(6)
_NO_LIMIT = (0.0, 1.0)  # the controller did not run: no limit, scale 1
_NO_WRENCH = Wrench(np.full(3, math.nan), np.full(3, math.nan), 0.0, 0)  # no reading


class ControlCore:
    """The chain and its state between cycles (loop thread only).

    clock: the time [s] a cycle is judged at when :meth:`step` gets no ``now`` (the
    readings' clock: ``time.monotonic``; tests give a scripted one)."""

    def __init__(self, cfg: Config, model: RobotModel | None = None,
                 clock: Callable[[], float] = time.monotonic):
        self.cfg = cfg
        self.clock = clock
        self.chain = CycleChain(cfg, model)
        self.dt = self.chain.dt
        self.model = self.chain.model
        self.controller = self.chain.controller
        self.wrench = self.chain.wrench
        self.cstate: CycleState = self.chain.initial_state()
        #: the parameters changed at run time (`mmctl set`): key -> value now
        self.changed: dict[str, object] = {}

    @property
    def state(self) -> ControllerState:
        return self.cstate.controller

    @property
    def wstate(self) -> WrenchState:
        return self.cstate.wrench

    # -- operator commands (loop thread) ------------------------------------------------
    @property
    def mode(self) -> str:
        return self.state.mode.value

    @property
    def switch(self) -> str:
        return self.state.switch.value

    @property
    def profile(self) -> str:
        """The limits' profile: "normal" or "reduced"."""
        return "reduced" if self.state.reduced else "normal"

    @property
    def caps(self) -> dict[str, float | None]:
        """The whole-body caps in force (energy [J], base and end-effector speed [m/s]),
        the profile's end-effector cap included."""
        c = self.controller.caps
        ee = min(c.ee_speed, self.cfg.limits.ee_linear_velocity)
        if self.state.reduced:
            ee = min(ee, self.cfg.limits.reduced_ee_speed)
        base = min(c.base_speed, self.cfg.limits.base_linear_velocity)
        return {"energy_J": None if math.isinf(c.energy) else round(c.energy, 4),
                "base_speed_m_s": round(base, 4), "ee_speed_m_s": round(ee, 4)}

    def set_profile(self, profile: str) -> None:
        """The limits' profile: "normal" or "reduced" (a lower cap is reached on the
        acceleration limits, never by a jump)."""
        self.cstate = self.cstate._replace(
            controller=self.controller.set_profile(self.state, profile))

    def prepare(self, key: str, value: object) -> tuple[Config, Controller]:
        """A run-time parameter change, the slow half (any thread): the configuration
        with ``key`` set (validated: ConfigError) and a controller built from it on a
        model of its own (the loop's model is the loop thread's scratch space)."""
        cfg = with_value(self.cfg, key, value)
        return cfg, Controller(cfg, RobotModel(cfg.robot))

    def install(self, cfg: Config, controller: Controller, key: str = "") -> None:
        """The quick half (loop thread): the new controller takes over the current
        state (the admittance's velocity, the last command, mode, switch, profile): no
        velocity jump; a lower cap or another weighting is reached on the acceleration
        limits as a mode change is.  ``key``: what changed (:attr:`changed` shows it)."""
        if key:
            self.changed[key] = get_value(cfg, key)
        self.cfg = cfg
        self.chain.cfg = cfg
        self.chain.controller = controller
        self.controller = controller

    def installed(self, cfg: Config, controller: Controller, key: str) -> None:
        """The update installed ``controller`` for ``cfg`` (``key`` changed): the core's
        view of it (:attr:`cfg`, :attr:`controller`, :attr:`changed`)."""
        self.changed[key] = get_value(cfg, key)
        self.cfg = cfg
        self.controller = controller

    @property
    def taring(self) -> bool:
        return self.wstate.tare_left > 0

    def set_mode(self, mode: str) -> None:
        """Another IDK strategy; the controller cross-fades (no velocity jump)."""
        self.cstate = self.cstate._replace(controller=self.controller.set_mode(self.state, mode))

    def set_switch(self, which: str) -> None:
        """manipulation / locomotion sub-mode of the switch strategy (cross-faded)."""
        self.cstate = self.cstate._replace(
            controller=self.controller.set_switch(self.state, which))

    def toggle_switch(self) -> None:
        self.cstate = self.cstate._replace(controller=self.controller.toggle_switch(self.state))

    def start_tare(self) -> None:
        """Average the next ``tare_samples`` fresh samples into the sensor bias."""
        self.cstate = self.cstate._replace(wrench=self.wrench.start_tare(self.wstate))

    def reset(self) -> None:
        """Controller at rest in the current mode and switch sub-mode (on enable)."""
        self.cstate = self.chain.at_rest(self.cstate)

    # -- the cycle ----------------------------------------------------------------------
    def step(self, arm: ArmState, wrench: Wrench, odom: Odometry, dt: float,
             active: bool, now: float | None = None, held: bool = True) -> CycleResult:
        """One cycle from the device readings; ``active``: the robot is armed; ``held``:
        the enabling switch is held (or there is none)."""
        t_now = self.clock() if now is None else now
        self.cstate, result = self.chain.cycle(
            self.cstate, Readings(arm, wrench, odom, dt, active, held), t_now)
        return result

    def condition(self, q: Vec) -> float:
        """Condition number of J J^T at ``q`` (the controller's singularity measure)."""
        return self.chain.condition(q)

    # -- telemetry ----------------------------------------------------------------------
    def fill_row(self, r: CycleResult, cycle: int, t: float, safety: str,
                 prev: tuple[float, ...], row: NDArray[np.float64]) -> None:
        """Write this cycle and the previous cycle's timing ``prev`` (latency, compute,
        slack, missed [ns]) into a telemetry row (:mod:`mmctl.telemetry.ring` layout) in
        place: the loop's telemetry hot path, one numpy call.

        The row holds what the cycle has at hand (world-frame positions; the consumer
        derives the base frame and the wheel speeds); ``v`` is the measured J(q) q̇ the
        cycle computed (:attr:`CycleResult.v`).
        """
        q = r.q
        mode = self.mode if self.mode != "switch" else f"switch/{self.switch}"
        v = r.v
        e = r.energy
        out = r.out
        limit = (tr.limit_code(out.limit), out.scale) if out is not None else _NO_LIMIT
        near = out.body[1] if out is not None and out.body is not None else math.nan
        raw = r.raw if r.raw is not None else _NO_WRENCH
        np.concatenate(((cycle, t, tr.mode_code(mode), tr.safety_code(safety), *prev), q,
                        r.f_h, r.v_d, v, r.qd_cmd, (e.total, e.arm, e.base), r.p, r.p_des,
                        limit, (near,), r.qd[:6], raw.force, raw.torque), out=row)

