"""The controller's part of a cycle, pure: ``controller.step(state, inputs) -> (state, outputs)``.

From the processed human wrench ``f_h`` and the measured ``q``, ``q̇`` to the joint
commands.  The whole cycle (the wrench pipeline from the sensor's raw sample, staleness
and fault conditions, then this) is :meth:`mmctl.control.cycle.CycleChain.cycle`, which
the daemon's loop, the study and the tests call::

    ctl = Controller(cfg)                 # builds the model and the solvers once
    state = ctl.initial_state()
    state, out = ctl.step(state, StepInputs(f_h, q, qdot, dt))
    state = ctl.set_mode(state, "locomotion")      # at run time, never a jump

A cycle: admittance (exact ZOH) -> v_d; model at the measured q -> J, M;
IDK strategy (cross-faded over ``idk.switch.blend_time`` whenever the active solver
changes) -> qdot_d; limits -> qdot; energies; faults.  On a non-finite number
(``NON_FINITE``) or a singular configuration (``SINGULAR``: the condition number of
the whole-body ``J J^T`` above ``safety.max_condition``) the outputs command zero
velocity, the admittance and the previous command are reset to zero, and ``fault``
names the cause; :meth:`Controller.step` never raises for these (a non-positive
``dt`` counts as non-finite; arrays of the wrong shape are a bug and raise ValueError).

Purity: the outputs depend only on ``(state, inputs)``; the controller object only
holds constants and scratch buffers.  States are frozen dataclasses with read-only
arrays.
"""

from __future__ import annotations

import dataclasses
import math
from enum import Enum
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

from mmctl.config import Config
from mmctl.config.control import Mode, SwitchMode
from mmctl.control.admittance import Admittance
from mmctl.control.body import BodyCheck, BodyState
from mmctl.control.energy import Energy, kinetic_energy
from mmctl.control.iso15066 import Caps, derive
from mmctl.control.limits import Limits
from mmctl.control.strategies import IdkStrategy, Problem, make_strategies
from mmctl.control.walls import Walls
from mmctl.errors import ConfigError, FaultCause, MmctlError
from mmctl.model.planar import point_to_world
from mmctl.model.robot import RobotModel, planar_pose

Vec = NDArray[np.float64]


#: The solvers, in the order of :attr:`ControllerState.weights`.
SOLVERS: tuple[str, ...] = (Mode.MIN_ENERGY.value, Mode.LOCOMOTION.value,
                            Mode.MANIPULATION.value, Mode.CONSTRAINED.value)


class UnknownMode(MmctlError, ValueError):
    """A mode name that does not exist; the message lists the valid ones."""


def _frozen(a: Vec) -> Vec:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclasses.dataclass(frozen=True, eq=False)
class ControllerState:
    """Everything that carries over from one cycle to the next (immutable).

    v: (6,) admittance twist [m/s, rad/s]; qdot: (9,) previous command after limits;
    mode: selected strategy; switch: sub-mode used when ``mode`` is SWITCH;
    weights: blend weight of each solver in :data:`SOLVERS` (sum 1; one-hot when no
    cross-fade is running); cycle: number of steps taken.  (Compared by identity:
    the fields hold arrays.)
    """

    v: Vec
    qdot: Vec
    mode: Mode
    switch: SwitchMode
    weights: tuple[float, float, float, float]
    cycle: int = 0
    reduced: bool = False
    """The reduced limits profile (``limits.reduced_ee_speed``) is selected."""
    body: BodyState | None = None
    """The self-collision check's last measure (:mod:`mmctl.control.body`)."""

    @property
    def target(self) -> str:
        """The solver the blend is heading to."""
        return _target(self.mode, self.switch)

    @property
    def blending(self) -> bool:
        """True while a cross-fade is in progress."""
        return max(self.weights) < 1.0


class StepInputs(NamedTuple):
    """f_h: (6,) processed human wrench in the control frame [N, N m]; q: (9,) measured
    configuration (arm [rad], base x, y [m], yaw [rad] in the world); qdot: (9,)
    measured velocities (arm [rad/s], base twist in the base frame); dt: period [s];
    hold: come to rest and stay there (the enabling switch is released): the desired
    velocity is zero, the admittance is reset, the limits decelerate the command."""

    f_h: Vec
    q: Vec
    qdot: Vec
    dt: float
    hold: bool = False


class StepOutputs(NamedTuple):
    """What one cycle commands and reports.

    v_d: (6,) admittance twist, control frame; qdot: (9,) command after limits;
    qdot_arm: (6,) [rad/s] for speedJ; base_twist: (3,) (vx, vy [m/s], wz [rad/s]) in
    the base frame; energy: E_K from the measured qdot; energy_cmd: E_K from the
    command (both with the paper's block-diagonal M) [J]; scale: velocity-limit scale
    of the IDK output (s_v * s_f, 1 = unlimited); accel_scale: acceleration blend s_a;
    p: (3,) tool position in the world [m]; p_des: (3,) FK(q_des) with the base at its
    current pose (so |p - p_des| is the paper's x_f); condition: condition number of
    J J^T; fault: the cause when the cycle was refused, else None; v: (6,) the measured
    end-effector twist J(q) qdot_measured, control frame [m/s, rad/s] (zeros when
    refused); limit: the limit that bound the command (:data:`~mmctl.control.limits.
    LIMIT_NAMES`, "" none).
    """

    v_d: Vec
    qdot: Vec
    qdot_arm: Vec
    base_twist: Vec
    energy: Energy
    energy_cmd: Energy
    scale: float
    accel_scale: float
    p: Vec
    p_des: Vec
    condition: float
    fault: FaultCause | None
    v: Vec
    limit: str = ""
    body: tuple[tuple[str, str], float] | None = None
    """The robot's two nearest parts and their distance [m] (:mod:`mmctl.control.body`;
    None when the check is off or the cycle was refused before it)."""


def _target(mode: Mode, switch: SwitchMode) -> str:
    target: str = switch.value if mode is Mode.SWITCH else mode.value
    return target


def _one_hot(name: str) -> tuple[float, float, float, float]:
    w = [0.0, 0.0, 0.0, 0.0]
    w[SOLVERS.index(name)] = 1.0
    return (w[0], w[1], w[2], w[3])


def _parse(enum: type[Enum], value: object) -> Enum:
    try:
        return enum(value.value if isinstance(value, Enum) else value)
    except ValueError:
        valid = ", ".join(repr(m.value) for m in enum)
        raise UnknownMode(f"unknown mode {value!r}; valid: {valid}") from None


#: [s] the time constant of the singularity braking's last approach
_SING_TAU = 0.05

#: The limits' profiles (``limits.profile``, ``mmctl profile``).
PROFILES: tuple[str, ...] = ("normal", "reduced")


def whole_body_caps(cfg: Config, arm_mass: float) -> Caps:
    """The whole-body caps: ``limits.energy`` / ``base_speed`` / ``ee_speed`` where
    given, else derived from ``limits.body_region`` (:func:`mmctl.control.iso15066.
    derive`) with the robot's masses: base, arm (``arm_mass`` [kg]) and handle."""
    lim = cfg.limits
    load = cfg.sensor.wrench.handle_mass
    d = derive(lim.body_region, cfg.robot.base_mass + arm_mass + load, arm_mass, load)
    return Caps(d.energy if lim.energy is None else lim.energy,
                d.base_speed if lim.base_speed is None else lim.base_speed,
                d.ee_speed if lim.ee_speed is None else lim.ee_speed)


_syev = lapack.dsyev
_ZERO_E = Energy(0.0, 0.0, 0.0)
_Z3 = _frozen(np.zeros(3))
_Z6 = _frozen(np.zeros(6))
_Z9 = _frozen(np.zeros(9))


class Controller:
    """The control chain of one cycle, built once from the configuration.

    model: an existing :class:`RobotModel` (one per thread: its Pinocchio data is
    scratch space); by default a new one from ``cfg.robot``.
    """

    def __init__(self, cfg: Config, model: RobotModel | None = None) -> None:
        self.cfg = cfg
        self.model = model if model is not None else RobotModel(cfg.robot)
        self.admittance = Admittance.from_config(cfg.admittance)
        self.caps = whole_body_caps(cfg, self.model.arm_mass)
        self.limits = Limits(cfg.limits, cfg.base.mecanum, cfg.arm.speedj_acceleration,
                             self.caps)
        reduced = self.caps._replace(ee_speed=min(self.caps.ee_speed,
                                                  cfg.limits.reduced_ee_speed))
        self.limits_reduced = Limits(cfg.limits, cfg.base.mecanum,
                                     cfg.arm.speedj_acceleration, reduced)
        self.strategies: dict[str, IdkStrategy] = make_strategies(cfg, self.limits)
        self._solvers = tuple(self.strategies[n] for n in SOLVERS)
        self.gain = np.array(cfg.idk.null_gain)
        self.q_des = self.model.q_des  # (9,) arm q_des, base part 0 (its gain is 0 by default)
        self.p_des_base = self.model.fk_base(self.q_des).translation.copy()
        self.blend_time = cfg.idk.switch.blend_time
        self.max_condition = cfg.safety.max_condition
        self.cond_stop = cfg.safety.brake_condition * cfg.safety.max_condition
        self.r_stop = 1.0 / math.sqrt(self.cond_stop)
        #: the braking is skipped below cond_stop / 400 (r above 20 r_stop: far from
        #: any singular pose); it costs one Jacobian, ~25 us a cycle
        self.brake_accel = 0.8 * min(min(cfg.limits.joint_acceleration),
                                     cfg.arm.speedj_acceleration)
        self.cond_watch = 1.0 / (20.0 * self.r_stop) ** 2
        self.body = BodyCheck(cfg, self.model) if cfg.safety.collision_check else None
        if self.body is not None:
            near = self.body.body.closest(self.q_des[:6])
            if near.distance < cfg.safety.collision_margin:
                raise ConfigError("robot.q_des", list(cfg.robot.q_des),
                                  f"puts the {near.pair[0]} and the {near.pair[1]} "
                                  f"{near.distance:.3f} m apart, inside "
                                  f"safety.collision_margin = {cfg.safety.collision_margin} m "
                                  "(`mmctl model distances --q ...` lists the pairs)")
        lim = cfg.limits
        self.walls = Walls.from_config(
            cfg.walls, min(self.caps.ee_speed, lim.ee_linear_velocity),
            min(lim.joint_acceleration) * 1.0,  # [rad/s^2 x 1 m] the joints' at 1 m
            min(self.caps.base_speed, lim.base_linear_velocity), lim.base_linear_acceleration)
        box = self.walls.box_distances(self.p_des_base) if self.walls is not None else ()
        if len(box) and min(box) <= 0.0:
            raise ConfigError("walls.ee_box", [list(r) for r in cfg.walls.ee_box or ()],
                              "must contain the tool point of robot.q_des (the null-space "
                              "term pulls the handle there), at "
                              f"{self.p_des_base.round(3).tolist()} m in the base frame")

    def use_strategy(self, name: str, strategy: IdkStrategy) -> None:
        """Run ``strategy`` as the solver ``name`` (one of :data:`SOLVERS`) from now on
        (the study's sweep: a variant of the min-energy solve)."""
        if name not in SOLVERS:
            raise ValueError(f"unknown solver {name!r}; one of {', '.join(SOLVERS)}")
        self.strategies[name] = strategy
        self._solvers = tuple(self.strategies[n] for n in SOLVERS)

    # --- state -----------------------------------------------------------------

    def initial_state(self, mode: Mode | str | None = None) -> ControllerState:
        """At rest, in ``mode`` (default ``idk.strategy``), switch in ``idk.switch.initial``."""
        m = _parse(Mode, mode if mode is not None else self.cfg.idk.strategy)
        sw = _parse(SwitchMode, self.cfg.idk.switch.initial)
        assert isinstance(m, Mode) and isinstance(sw, SwitchMode)
        return ControllerState(_Z6, _Z9, m, sw, _one_hot(_target(m, sw)), 0,
                               self.cfg.limits.profile == "reduced")

    def set_profile(self, state: ControllerState, profile: str) -> ControllerState:
        """Select the limits' profile ("normal" or "reduced"); a lower cap is reached on
        the acceleration limits, never by a jump."""
        if profile not in PROFILES:
            raise UnknownMode(f"unknown profile {profile!r}; valid: "
                              f"{', '.join(repr(p) for p in PROFILES)}")
        return dataclasses.replace(state, reduced=profile == "reduced")

    def set_mode(self, state: ControllerState, mode: Mode | str) -> ControllerState:
        """Select another strategy; the command cross-fades over ``blend_time``."""
        m = _parse(Mode, mode)
        assert isinstance(m, Mode)
        return dataclasses.replace(state, mode=m)

    def set_switch(self, state: ControllerState, sub: SwitchMode | str) -> ControllerState:
        """Set the switch sub-mode (manipulation/locomotion); used while mode is SWITCH."""
        s = _parse(SwitchMode, sub)
        assert isinstance(s, SwitchMode)
        return dataclasses.replace(state, switch=s)

    def toggle_switch(self, state: ControllerState) -> ControllerState:
        """manipulation <-> locomotion (the handle button)."""
        other = (SwitchMode.LOCOMOTION if state.switch is SwitchMode.MANIPULATION
                 else SwitchMode.MANIPULATION)
        return dataclasses.replace(state, switch=other)

    def _blend(self, weights: tuple[float, ...], target: str, dt: float) -> tuple[float, ...]:
        """Move the weights linearly toward the one-hot target by dt / blend_time."""
        t = SOLVERS.index(target)
        wt = weights[t]
        if wt >= 1.0:
            return weights
        new_t = min(1.0, wt + dt / self.blend_time)
        if new_t >= 1.0:
            return _one_hot(target)
        k = (1.0 - new_t) / (1.0 - wt)
        return tuple(new_t if i == t else w * k for i, w in enumerate(weights))

    # --- the cycle -------------------------------------------------------------
    def _fault(self, state: ControllerState, cause: FaultCause, cond: float,
               weights: tuple[float, ...],
               body: tuple[tuple[str, str], float] | None = None
               ) -> tuple[ControllerState, StepOutputs]:
        new = dataclasses.replace(state, v=_Z6, qdot=_Z9, weights=weights,  # type: ignore[arg-type]
                                  cycle=state.cycle + 1)
        out = StepOutputs(_Z6, _Z9, _Z6, _Z3, _ZERO_E, _ZERO_E, 0.0, 0.0, _Z3, _Z3, cond, cause,
                          _Z6, "", body)
        return new, out

    def step(self, state: ControllerState, inp: StepInputs) -> tuple[ControllerState, StepOutputs]:
        """One cycle (see the module docstring)."""
        f_h = np.asarray(inp.f_h, dtype=float)
        q = np.asarray(inp.q, dtype=float)
        qd_meas = np.asarray(inp.qdot, dtype=float)
        dt = float(inp.dt)
        weights = self._blend(state.weights, state.target, dt) if dt > 0.0 else state.weights
        if f_h.shape != (6,) or q.shape != (9,) or qd_meas.shape != (9,):
            raise ValueError(f"step inputs must be f_h (6,), q (9,), qdot (9,); got "
                             f"{f_h.shape}, {q.shape}, {qd_meas.shape}")  # a bug, not a fault
        # x @ x is finite iff every entry is (for physically sized values): one cheap check
        if not (math.isfinite(f_h @ f_h + q @ q + qd_meas @ qd_meas + dt) and dt > 0.0):
            return self._fault(state, FaultCause.NON_FINITE, math.nan, weights)

        v_d = self.admittance.step(state.v, f_h, dt)
        kin = self.model.update(q)
        walled = False
        if self.walls is not None and not inp.hold:  # the admittance's own state too
            v_d, in_box = self.walls.filter_box(v_d, kin.p_base)
            v_d, in_area = self.walls.filter_twist_area(v_d, q)
            walled = in_box or in_area
        J = kin.J
        w, _, info = _syev(J.dot(J.T), 0)  # no eigenvectors
        lo, hi = float(w[0]), float(w[-1])
        if info != 0 or not math.isfinite(hi):
            return self._fault(state, FaultCause.NON_FINITE, math.nan, weights)
        cond = hi / lo if lo > 0.0 else math.inf
        if cond > self.max_condition:
            return self._fault(state, FaultCause.SINGULAR, cond, weights)

        qdot_d: Vec | None = None
        if inp.hold:  # released: no admittance, no null-space motion; the limits brake
            v_d = np.zeros(6)
            qdot_d = np.zeros(9)
        else:
            z = self.gain * (self.q_des - q)
            problem = Problem(kin, v_d, q, state.qdot, dt, z)
            for wgt, solver in zip(weights, self._solvers):
                if wgt >= 1.0:  # no cross-fade running: the one solver
                    qdot_d = solver.solve(problem)
                    break
                if wgt > 0.0:
                    x = solver.solve(problem)
                    qdot_d = wgt * x if qdot_d is None else qdot_d + wgt * x
        assert qdot_d is not None
        if self.walls is not None:
            qdot_d, at_edge = self.walls.clamp_base(qdot_d, q)
            walled = walled or at_edge
        limits = self.limits_reduced if state.reduced else self.limits
        lim = limits.apply(qdot_d, state.qdot, q, J, dt, kin.M_a, kin.M_b)
        qdot = lim.qdot
        if self.walls is not None:  # again: the acceleration blend scales the whole
            qdot, at_edge = self.walls.clamp_base(qdot, q)  # change, the arm's too
            walled = walled or at_edge
        if walled and not lim.limit:
            lim = lim._replace(limit="wall")
        if cond > self.cond_watch:
            s_c = self._singularity_scale(q, qdot, cond)
            if s_c < 1.0:
                qdot = s_c * qdot
                lim = lim._replace(final_scale=lim.final_scale * s_c, limit="singularity")
        body = None
        body_state = state.body
        if self.body is not None:
            body_state, brake = self.body.brake(state.body, q[:6], qdot[:6], state.cycle)
            if brake.pair is not None:
                body = (brake.pair, brake.distance)
            if brake.fault:
                return self._fault(state, FaultCause.SELF_COLLISION, cond, weights, body)
            if brake.qdot_arm is not None:
                qdot = np.concatenate((brake.qdot_arm, qdot[6:]))
                lim = lim._replace(limit="self_collision")
            if brake.scale < 1.0:
                qdot = brake.scale * qdot
                lim = lim._replace(final_scale=lim.final_scale * brake.scale,
                                   limit="self_collision")
        if not math.isfinite(qdot @ qdot + v_d @ v_d):
            return self._fault(state, FaultCause.NON_FINITE, cond, weights)

        e_meas = kinetic_energy(kin.M_a, kin.M_b, qd_meas)
        e_cmd = kinetic_energy(kin.M_a, kin.M_b, qdot)
        p_des = point_to_world(q[6], q[7], q[8], self.p_des_base)
        v_d.setflags(write=False)
        qdot.setflags(write=False)
        new = ControllerState(v_d, qdot, state.mode, state.switch, weights,  # type: ignore[arg-type]
                              state.cycle + 1, state.reduced, body_state)
        out = StepOutputs(v_d, qdot, qdot[:6], qdot[6:], e_meas, e_cmd, lim.scale * lim.final_scale,
                          lim.accel_scale, kin.p, p_des, cond, None, J.dot(qd_meas), lim.limit,
                          body)
        return new, out

    def _singularity_scale(self, q: Vec, qdot: Vec, cond: float) -> float:
        """Singularity braking: the largest s in [0, 1] for which the command ``s qdot``
        approaches a singular pose no faster than a braking on 80 % of the joints'
        acceleration limit allows, to rest at ``cond_stop``.

        The distance is r = 1 / sqrt(cond) = sigma_min / sigma_max of J, which falls
        about linearly with the joint angle to a singular pose (cond grows as its
        inverse square); its rate along the command comes from J one small step ahead
        (at most 1 mrad of any joint: a far look-ahead can land past the singular pose
        and see the condition fall).  With k = |r'| / max|qdot_arm| (r per radian along
        the command), the speed toward r_stop is bounded by
        min(sqrt(2 k a (r - r_stop)), (r - r_stop) / tau): in joint space the usual
        sqrt(2 a d) curve, ending in an exponential approach (tau 50 ms).  1 when the
        command moves away (r rising)."""
        speed: float = max(map(abs, qdot[:6].tolist()))
        if speed <= 0.0:
            return 1.0
        r = 1.0 / math.sqrt(cond)
        h = min(0.01, 1e-3 / speed)
        r_next = 1.0 / math.sqrt(self.model.condition(q + h * qdot))  # 0 where singular
        rate = (r - r_next) / h  # [1/s] > 0: toward the singular pose
        if not rate > 0.0:
            return 1.0
        room = r - self.r_stop
        if room <= 0.0:
            return 0.0
        k = rate / speed
        allowed = min(math.sqrt(2.0 * k * self.brake_accel * room), room / _SING_TAU)
        return min(1.0, allowed / rate)

    # --- helpers for the simulator and tests -----------------------------------
    def p_des(self, q: Vec) -> Vec:
        """FK(q_des) (3,) in the world with the base at ``q[6:9]``."""
        p: Vec = (planar_pose(q[6], q[7], q[8]) * self.model.fk_base(self.q_des)).translation.copy()
        return p
