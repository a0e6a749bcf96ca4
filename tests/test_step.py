"""The pure control cycle: determinism, faults, mode changes without jumps, closed loop."""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest

from mmctl.config import Config, config_from_dict
from mmctl.control.step import (
    Controller,
    ControllerState,
    Mode,
    StepInputs,
    SwitchMode,
    UnknownMode,
)
from mmctl.control.strategies import Problem
from mmctl.errors import FaultCause

T = 0.002
PUSH = np.array([15.0, 5.0, 0.0, 0.0, 0.0, 0.0])


#: The defaults without the hand-guiding caps (limits.body_region: none): these tests are
#: about the chain, not the caps (tests/test_caps.py)
UNCAPPED = config_from_dict({"limits": {"body_region": "none"}})


@pytest.fixture(scope="module")
def ctl() -> Controller:
    return Controller(UNCAPPED)


def _plant(q: np.ndarray, qdot: np.ndarray, dt: float) -> np.ndarray:
    """Integrate whole-body velocities (base twist in the base frame) for dt [s]."""
    out = q + dt * qdot
    c, s = math.cos(q[8]), math.sin(q[8])
    out[6] = q[6] + dt * (c * qdot[6] - s * qdot[7])
    out[7] = q[7] + dt * (s * qdot[6] + c * qdot[7])
    return out


def _run(ctl: Controller, state: ControllerState, q: np.ndarray, n: int, f=PUSH,
         qdot=None, hook=None):
    qdot = np.zeros(9) if qdot is None else qdot
    outs = []
    for k in range(n):
        if hook is not None:
            state = hook(k, state)
        state, out = ctl.step(state, StepInputs(f, q, qdot, T))
        outs.append(out)
        q, qdot = _plant(q, out.qdot, T), out.qdot.copy()
    return state, q, outs


def test_step_is_deterministic_and_pure(ctl: Controller) -> None:
    other = Controller(UNCAPPED)
    for mode in Mode:
        s1 = ctl.initial_state(mode)
        s2 = other.initial_state(mode)
        q = ctl.q_des + np.array([0.1, -0.1, 0.05, 0.0, 0.1, 0.0, 0.5, -0.2, 0.3])
        f, qd = PUSH.copy(), np.full(9, 0.01)
        keep = (f.copy(), q.copy(), qd.copy())
        for _ in range(50):
            a_state, a = ctl.step(s1, StepInputs(f, q, qd, T))
            b_state, b = other.step(s2, StepInputs(f, q, qd, T))
            again_state, again = ctl.step(s1, StepInputs(f, q, qd, T))  # same call twice
            for x, y, z in zip(a, b, again):
                if isinstance(x, np.ndarray):
                    assert np.array_equal(x, y) and np.array_equal(x, z)
                else:
                    assert x == y == z
            for field in dataclasses.fields(ControllerState):
                x, y = getattr(a_state, field.name), getattr(again_state, field.name)
                assert np.array_equal(x, y) if isinstance(x, np.ndarray) else x == y
            s1, s2 = a_state, b_state
        for before, after in zip(keep, (f, q, qd)):
            assert np.array_equal(before, after)  # inputs untouched
        with pytest.raises(ValueError):
            s1.qdot[0] = 1.0  # states are read-only
        with pytest.raises(dataclasses.FrozenInstanceError):
            s1.cycle = 0  # type: ignore[misc]


@pytest.mark.parametrize("where", ["f_h", "q", "qdot", "dt"])
@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_non_finite_input_gives_zero_command_and_a_fault(ctl: Controller, where, bad) -> None:
    state, _, _ = _run(ctl, ctl.initial_state(), ctl.q_des.copy(), 20)  # in motion
    args = {"f_h": PUSH.copy(), "q": ctl.q_des.copy(), "qdot": np.zeros(9), "dt": T}
    if where == "dt":
        args["dt"] = bad
    else:
        args[where][2] = bad
    new, out = ctl.step(state, StepInputs(**args))
    assert out.fault is FaultCause.NON_FINITE
    assert not out.qdot.any() and not out.qdot_arm.any() and not out.base_twist.any()
    assert not out.v_d.any()
    assert not new.qdot.any() and not new.v.any()  # restart from rest after a fault
    assert new.cycle == state.cycle + 1


def test_singular_configuration_gives_zero_command_and_a_fault() -> None:
    strict = Controller(config_from_dict({"safety": {"max_condition": 2.0}}))
    _state, out = strict.step(strict.initial_state(), StepInputs(PUSH, strict.q_des, np.zeros(9), T))
    assert out.fault is FaultCause.SINGULAR and out.condition > 2.0
    assert not out.qdot.any()
    ok = Controller(UNCAPPED)
    _, out = ok.step(ok.initial_state(), StepInputs(PUSH, ok.q_des, np.zeros(9), T))
    assert out.fault is None and 1.0 < out.condition < 100.0


def test_outputs_are_consistent(ctl: Controller) -> None:
    state, q, outs = _run(ctl, ctl.initial_state(), ctl.q_des.copy(), 100)
    state, out = ctl.step(state, StepInputs(PUSH, q, outs[-1].qdot, T))
    outs.append(out)
    assert np.allclose(out.p, ctl.model.position(q), atol=1e-12)
    assert np.allclose(out.p_des, ctl.p_des(q), atol=1e-12)
    assert np.array_equal(out.qdot_arm, out.qdot[:6])
    assert np.array_equal(out.base_twist, out.qdot[6:])
    assert out.v_d.shape == (6,) and out.p.shape == (3,) and out.p_des.shape == (3,)
    assert np.allclose(out.v_d, state.v)
    # the measured end-effector twist is J(q) times the measured velocities
    assert np.allclose(out.v, ctl.model.jacobian(q) @ outs[-2].qdot, atol=1e-12)
    assert out.energy_cmd.total == pytest.approx(out.energy_cmd.arm + out.energy_cmd.base)
    assert 0.0 < out.scale <= 1.0 and 0.0 < out.accel_scale <= 1.0
    # measured energy uses the measured velocities given as input (here the previous command)
    assert out.energy.total == pytest.approx(outs[-2].energy_cmd.total, rel=0.05)
    with pytest.raises(ValueError, match="f_h \\(6,\\)"):
        ctl.step(state, StepInputs(np.zeros(3), q, np.zeros(9), T))
    with pytest.raises(UnknownMode, match="valid: 'min-energy'"):
        ctl.set_mode(state, "fastest")
    with pytest.raises(UnknownMode, match="'manipulation', 'locomotion'"):
        ctl.set_switch(state, "both")


def _without_accel_limits(cfg: Config) -> Config:
    """``cfg`` with its acceleration limits switched off (1e6): past the hardware's, so no
    configuration file may say so (the config rejects it); built around the validation."""
    limits = dataclasses.replace(cfg.limits, joint_acceleration=(1e6,) * 6,
                                 base_linear_acceleration=1e6, base_angular_acceleration=1e6)
    return dataclasses.replace(cfg, limits=limits)


def _no_accel_limits() -> Controller:
    """Acceleration limits would hide a jump: switch them off to test the blend itself."""
    return Controller(_without_accel_limits(UNCAPPED))


def _max_step_change(outs) -> float:
    return max(np.abs(b.qdot - a.qdot).max() for a, b in itertools.pairwise(outs))


@pytest.mark.parametrize("change", ["toggle", "set_mode", "back_and_forth"])
def test_mode_changes_mid_motion_never_jump(change: str) -> None:
    ctl = _no_accel_limits()
    q = ctl.q_des.copy()
    state = ctl.initial_state(Mode.SWITCH)
    assert state.switch is SwitchMode.MANIPULATION
    hold = np.zeros(9)  # q held still: every change of the command comes from the blend
    for _ in range(500):  # admittance settled: v_d constant
        state, out0 = ctl.step(state, StepInputs(PUSH, q, hold, T))
    if change == "toggle":
        state = ctl.toggle_switch(state)
    elif change == "set_mode":
        state = ctl.set_mode(state, "min-energy")
    n_blend = round(ctl.blend_time / T)

    def hook(k, s):
        if change == "back_and_forth" and k == 0:
            return ctl.toggle_switch(s)
        if change == "back_and_forth" and k == n_blend // 3:
            return ctl.toggle_switch(s)  # back again in mid-blend
        return s

    outs = [out0]
    for k in range(2 * n_blend):
        state = hook(k, state)
        state, out = ctl.step(state, StepInputs(PUSH, q, hold, T))
        outs.append(out)
    first, last = outs[0].qdot, outs[-1].qdot
    assert all(o.scale == 1.0 for o in outs)  # no velocity limit in play
    # the two strategies' commands at this (q, v_d)
    other = ("min-energy" if change == "set_mode" else "locomotion")
    problem = Problem(ctl.model.update(q), outs[0].v_d, q, hold, T,
                      ctl.gain * (ctl.q_des - q))
    gap = np.abs(ctl.strategies[other].solve(problem) - first).max()
    assert gap > 0.01  # the two strategies really differ
    if change != "back_and_forth":
        assert np.abs(last - first).max() == pytest.approx(gap, rel=1e-6)
    # the command moves by at most dt/blend_time of the gap per cycle
    # (1e-6: the admittance is settled to ~1e-8, not exactly)
    assert _max_step_change(outs) <= gap * T / ctl.blend_time * (1 + 1e-6)
    assert max(state.weights) == 1.0 and not state.blending
    # the blend really takes blend_time: halfway through, the command is about halfway
    if change == "toggle":
        mid = outs[n_blend // 2].qdot
        assert np.abs(mid - 0.5 * (first + last)).max() < 1e-9 + 1e-6 * gap


def test_without_a_blend_the_same_toggle_jumps() -> None:
    """Control for the test above: blend_time = dt makes the toggle a one-cycle step."""
    cfg = _without_accel_limits(config_from_dict({"idk": {"switch": {"blend_time": T}}}))
    ctl = Controller(cfg)
    q, hold = ctl.q_des.copy(), np.zeros(9)
    state = ctl.initial_state(Mode.SWITCH)
    for _ in range(500):
        state, a = ctl.step(state, StepInputs(PUSH, q, hold, T))
    state, b = ctl.step(ctl.toggle_switch(state), StepInputs(PUSH, q, hold, T))
    assert np.abs(b.qdot - a.qdot).max() > 0.01


def test_closed_loop_min_energy_spends_less_than_locomotion(ctl: Controller) -> None:
    """A steady 15.8 N push for 2 s: locomotion moves the base and keeps the arm at q_des;
    min-energy moves the arm first and stores far less kinetic energy."""
    res = {}
    for mode in ("locomotion", "min-energy", "constrained-min-energy"):
        _, q, outs = _run(ctl, ctl.initial_state(mode), ctl.q_des.copy(), 1000)
        assert all(o.fault is None for o in outs)
        res[mode] = (np.mean([o.energy_cmd.total for o in outs]), q)
    e_loco, q_loco = res["locomotion"]
    e_min, q_min = res["min-energy"]
    assert e_min < 0.5 * e_loco
    assert np.abs(q_loco[:6] - ctl.q_des[:6]).max() < 0.02  # the arm stays near q_des
    assert np.linalg.norm(q_loco[6:8]) > 2 * np.linalg.norm(q_min[6:8])  # the base moved
    assert res["constrained-min-energy"][0] == pytest.approx(e_min, rel=0.05)
