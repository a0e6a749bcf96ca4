"""The whole control chain as one pure cycle (`mmctl.control.cycle`), driven by scripted
readings and a scripted clock: exact cycle counts, no threads, no sleeps, no retries."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest

from mmctl.config import config_from_dict
from mmctl.control.cycle import CycleChain, CycleResult, CycleState, Readings
from mmctl.errors import FaultCause
from mmctl.types import ArmState, Odometry, Vec, Wrench

DT = 0.002
Q_SINGULAR = [0.0, -np.pi / 2, 0.0, -np.pi / 2, 0.0, 0.0]  # stretched up, wrist aligned


@dataclass
class Script:
    """A robot that holds still and a sensor whose sample is chosen per cycle."""

    chain: CycleChain
    state: CycleState
    t: float = 100.0
    seq: int = 0
    q: Vec = field(default_factory=lambda: np.zeros(6))
    bias: Vec = field(default_factory=lambda: np.zeros(6))

    def readings(self, force: Vec, active: bool, fresh: bool = True,
                 q: Vec | None = None) -> Readings:
        """Readings at the script's clock: ``force`` [N] in the sensor frame on top of
        the handle's weight and the sensor bias (a new sample unless ``fresh`` is False)."""
        qa = self.q if q is None else np.asarray(q, dtype=float)
        r = self.chain.model.fk_base(np.concatenate((qa, np.zeros(3))), "sensor").rotation
        raw = self.chain.wrench.gravity_wrench(r) + self.bias
        raw[:3] += force
        if fresh:
            self.seq += 1
        arm = ArmState(qa, np.zeros(6), self.t, 2, 1)
        return Readings(arm, Wrench(raw[:3], raw[3:], self.t, self.seq),
                        Odometry(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, self.t), DT, active)

    def step(self, force: Vec | None = None, active: bool = True, fresh: bool = True,
             q: Vec | None = None) -> CycleResult:
        force = np.zeros(3) if force is None else force
        self.t += DT
        self.state, out = self.chain.cycle(self.state, self.readings(force, active, fresh, q),
                                           self.t)
        return out


@pytest.fixture(scope="module")
def chain() -> CycleChain:
    return CycleChain(config_from_dict({"sensor": {"wrench": {
        "stale_timeout": 0.01, "deadband_force": 0.5, "tare_samples": 10}}}))


@pytest.fixture
def script(chain: CycleChain) -> Script:
    q = np.array(chain.cfg.robot.q_des, dtype=float)[:6]
    return Script(chain, chain.initial_state(), q=q)


PUSH = np.array([20.0, 0.0, 0.0])


def test_the_same_state_and_readings_give_the_same_result(script: Script) -> None:
    for _ in range(5):
        script.step(PUSH)
    state, readings = script.state, script.readings(PUSH, True)
    a_state, a = script.chain.cycle(state, readings, script.t + DT)
    b_state, b = script.chain.cycle(state, readings, script.t + DT)  # the input state is kept
    assert np.array_equal(a.qd_cmd, b.qd_cmd) and np.array_equal(a.f_h, b.f_h)
    assert np.array_equal(a_state.controller.v, b_state.controller.v)
    assert a.fault is None and np.abs(a.qd_arm).max() > 0


def test_armed_a_push_moves_and_the_release_brings_it_to_rest(script: Script) -> None:
    first = script.step(PUSH)
    assert first.fault is None and np.abs(first.qd_arm).max() > 0  # the very first cycle
    for _ in range(200):
        moving = script.step(PUSH)
    # the push is in the sensor frame; v_d in the control frame: compare magnitudes
    steady = 20.0 / script.chain.cfg.admittance.damping[0]  # f / B
    assert np.linalg.norm(moving.v_d[:3]) == pytest.approx(steady, rel=0.1)
    for _ in range(500):  # 1 s without a push: 19 admittance time constants (M/B)
        rest = script.step()
    assert abs(rest.v_d).max() < 1e-4


def test_disarmed_nothing_is_commanded(script: Script) -> None:
    for _ in range(20):
        out = script.step(PUSH, active=False)
        assert out.fault is None and out.out is None
        assert not out.qd_cmd.any() and not out.qd_arm.any() and not out.twist.any()
    assert np.linalg.norm(out.f_h[:3]) == pytest.approx(20.0, rel=0.05)  # still measured
    assert not script.state.controller.v.any()  # held at rest: arming starts from rest


def test_a_stale_sensor_is_a_fault_in_the_first_cycle_past_the_timeout(script: Script) -> None:
    script.step(PUSH)
    timeout = script.chain.cfg.sensor.wrench.stale_timeout
    late = math.floor(timeout / DT + 1e-9) + 1  # the first cycle whose age > timeout
    outs = [script.step(PUSH, fresh=False) for _ in range(late)]
    assert [o.fault for o in outs[:-1]] == [None] * (late - 1)
    assert outs[-1].fault is FaultCause.SENSOR_STALE
    assert not outs[-1].qd_cmd.any() and not outs[-1].twist.any()
    assert script.step(PUSH).fault is None  # a fresh sample again: the condition clears


@pytest.mark.parametrize(("force", "cause"), [
    ([0.0, 0.0, 200.0], FaultCause.WRENCH_LIMIT),
    ([0.0, 0.0, 1000.0], FaultCause.SENSOR_SATURATION),  # beyond the Axia80's 900 N
    ([math.nan, 0.0, 0.0], FaultCause.NON_FINITE),
])
def test_a_bad_wrench_is_a_fault_in_its_own_cycle(script: Script, force: list[float],
                                                  cause: FaultCause) -> None:
    for _ in range(5):
        assert script.step(PUSH).fault is None
    out = script.step(np.array(force))
    assert out.fault is cause, out.fault_details
    assert not out.qd_cmd.any() and not out.twist.any() and not out.qd_arm.any()
    assert not script.state.controller.v.any()  # at rest for the next enable


def test_non_finite_joints_are_a_fault(script: Script) -> None:
    q = script.q.copy()
    q[2] = math.nan
    out = script.step(PUSH, q=q)
    assert out.fault is FaultCause.NON_FINITE and out.fault_details == {"where": "measured q/qd"}


def test_a_singular_pose_refuses_while_disarmed(script: Script) -> None:
    out = script.step(active=False, q=np.array(Q_SINGULAR))
    assert out.fault is FaultCause.SINGULAR
    assert out.fault_details["condition"] > script.chain.cfg.safety.max_condition


def test_a_tare_takes_exactly_its_fresh_samples_and_removes_the_bias(script: Script) -> None:
    script.bias = np.array([3.0, -2.0, 5.0, 0.0, 0.0, 0.0])
    for _ in range(200):  # the low-pass settles on the bias
        out = script.step(active=False)
    assert np.linalg.norm(out.f_h[:3]) == pytest.approx(np.linalg.norm(script.bias[:3]),
                                                        abs=0.6)
    n = script.chain.cfg.sensor.wrench.tare_samples
    script.state = script.state._replace(
        wrench=script.chain.wrench.start_tare(script.state.wrench))
    taring = []
    for k in range(2 * n + 3):
        out = script.step(active=False, fresh=(k % 2 == 0))  # every other sample repeats
        taring.append(out.taring)
    # the n-th fresh sample (cycle 2 (n - 1), still a taring cycle) ends it: the
    # repeated samples in between do not count
    assert taring == [True] * (2 * n - 1) + [False] * 4, taring
    for _ in range(200):  # the low-pass settles on the tared value
        out = script.step(active=False)
    assert np.abs(out.f_h[:3]).max() < 1e-6


@pytest.mark.parametrize("scaling", [0.4, 0.0])
def test_the_arms_speed_scaling_slows_the_base_with_it(script: Script, scaling: float) -> None:
    """The controller runs speedJ at ``speed_scaling`` of its speeds (speed slider,
    reduced mode): the base's twist is scaled alike, so the whole body keeps the motion
    the IDK solved; the arm's command and the controller's state are not (the
    controller scales the arm itself; nothing winds up)."""
    for _ in range(100):
        script.step(PUSH)
    state, r = script.state, script.readings(PUSH, True)
    t = script.t + DT
    _, full = script.chain.cycle(state, r, t)
    slow_state, slow = script.chain.cycle(
        state, r._replace(arm=r.arm._replace(speed_scaling=scaling)), t)
    assert np.abs(full.twist).max() > 0
    np.testing.assert_allclose(slow.twist, scaling * full.twist, atol=1e-15)
    np.testing.assert_array_equal(slow.qd_arm, full.qd_arm)
    np.testing.assert_array_equal(slow_state.controller.qdot, script.chain.cycle(
        state, r, t)[0].controller.qdot)
    _, bad = script.chain.cycle(state, r._replace(arm=r.arm._replace(speed_scaling=math.nan)), t)
    assert bad.fault is FaultCause.NON_FINITE and not bad.twist.any()
