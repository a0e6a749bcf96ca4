"""Simulated human: minimum-jerk profile, reaction delay, task completion, switch policy,
and no knowledge of the control approach."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from mmctl.sim.human import (
    QUICK_HOLES,
    HandleObservation,
    HumanAction,
    HumanParams,
    Phase,
    SimulatedHuman,
    SwitchPolicy,
    Task,
    min_jerk,
    peg_in_hole_task,
)

DT = 0.002
START = np.array([0.5, 0.2, 1.0])
DOWN = np.array([0.0, 0.0, -1.0])


def test_min_jerk_endpoints_and_peak() -> None:
    assert min_jerk(0.0) == (0.0, 0.0, 0.0)
    assert min_jerk(1.0) == pytest.approx((1.0, 0.0, 0.0))
    sig, dsig, ddsig = min_jerk(0.5)
    assert sig == pytest.approx(0.5)
    assert dsig == pytest.approx(1.875)  # peak speed = 1.875 x mean speed
    assert ddsig == pytest.approx(0.0)
    assert min_jerk(-1.0) == min_jerk(0.0) and min_jerk(2.0) == min_jerk(1.0)
    s = np.linspace(0.0, 1.0, 201)
    sig = np.array([min_jerk(x)[0] for x in s])
    assert np.all(np.diff(sig) >= 0.0)
    # derivative consistent with finite differences
    num = np.gradient(sig, s)
    ana = np.array([min_jerk(x)[1] for x in s])
    np.testing.assert_allclose(num[1:-1], ana[1:-1], atol=2e-3)


class PointRobot:
    """A 3-D admittance point (M v' + B v = f), like the controller with perfect tracking;
    with a dead band ``deadband`` [N] on the force, as the robot's wrench pipeline has."""

    def __init__(self, x0: np.ndarray, m: float = 4.0, b: float = 75.0,
                 deadband: float = 0.0) -> None:
        self.x, self.v, self.m, self.b = x0.copy(), np.zeros(3), m, b
        self.deadband = deadband

    def step(self, f: np.ndarray, dt: float) -> None:
        n = float(np.linalg.norm(f))
        f = f * (max(n - self.deadband, 0.0) / n) if n > 0.0 else f
        a = np.exp(-self.b * dt / self.m)
        self.v = a * self.v + (1 - a) * f / self.b
        self.x = self.x + self.v * dt


def run(human: SimulatedHuman, robot: PointRobot, t_max: float) -> list[tuple[float, HumanAction]]:
    out = []
    for k in range(int(t_max / DT)):
        t = k * DT
        act = human.update(HandleObservation(t, robot.x, robot.v, np.zeros(3)))
        out.append((t, act))
        if act.done:
            break
        robot.step(act.force, DT)
    return out


def quick_task() -> Task:
    return peg_in_hole_task(START, DOWN, 0.0, QUICK_HOLES)


def test_task_layout() -> None:
    task = peg_in_hole_task(START, DOWN, 0.0, ((0.2, 0.3),), depth=0.05)
    (h,) = task.holes
    np.testing.assert_allclose(h.approach, START + [0.2, 0.3, 0.0])  # u = heading x, w = left y
    np.testing.assert_allclose(h.bottom, START + [0.2, 0.3, -0.05])
    task = peg_in_hole_task(START, DOWN, np.pi / 2, ((0.2, 0.3),))
    np.testing.assert_allclose(task.holes[0].approach, START + [-0.3, 0.2, 0.0], atol=1e-12)
    wall = peg_in_hole_task(START, [1.0, 0.0, 0.0], 0.0, ((0.1, 0.4),))  # wall ahead
    np.testing.assert_allclose(wall.holes[0].approach, START + [0.0, 0.4, 0.1], atol=1e-12)


def test_reaction_delay_then_pull() -> None:
    p = HumanParams(reaction_time=0.4)
    trace = run(SimulatedHuman(p, quick_task()), PointRobot(START), 1.0)
    for t, act in trace:
        if t < 0.4 - 1e-9:
            assert act.phase is Phase.REACT
            np.testing.assert_array_equal(act.force, 0.0)
    later = [a for t, a in trace if t > 0.5]
    assert all(a.phase is Phase.REACH for a in later)
    assert np.linalg.norm(later[-1].force) > 1.0


def test_completes_the_task_with_plausible_forces() -> None:
    p = HumanParams()
    task = quick_task()
    human = SimulatedHuman(p, task)
    robot = PointRobot(START)
    trace = run(human, robot, 60.0)
    assert trace[-1][1].done and human.finish_time is not None
    assert human.finish_time == pytest.approx(trace[-1][0], abs=2 * DT)
    # the peg ends in the last hole
    np.testing.assert_allclose(robot.x, task.holes[-1].bottom, atol=p.insertion_tolerance)
    forces = np.array([np.linalg.norm(a.force) for _, a in trace])
    assert forces.max() <= p.f_max + 1e-9
    assert 3.0 < forces.mean() < 30.0
    phases = [a.phase for _, a in trace]
    for ph in (Phase.REACT, Phase.REACH, Phase.INSERT, Phase.DWELL, Phase.EXTRACT):
        assert ph in phases
    # dwell lasts dwell_time per hole
    n_dwell = sum(1 for ph in phases if ph is Phase.DWELL)
    assert n_dwell * DT == pytest.approx(len(task.holes) * p.dwell_time, abs=4 * DT)


def test_a_person_pushes_through_the_robots_dead_band() -> None:
    """K |gap| falls under a 2 N dead band 5.7 mm short of a goal (K = 350 N/m), outside
    the 5 mm insertion tolerance: the person's effort build-up finishes the task anyway,
    each correction pushing just past the dead band (no more than it takes)."""
    p = HumanParams()
    assert p.stiffness * p.insertion_tolerance < 2.0
    human = SimulatedHuman(p, quick_task())
    robot = PointRobot(START, deadband=2.0)
    trace = run(human, robot, 60.0)
    assert trace[-1][1].done, trace[-1][1].phase
    assert human.finish_time is not None and human.finish_time < 30.0
    settling = [np.linalg.norm(a.force) for _, a in trace if a.phase is Phase.DWELL]
    assert max(settling) < 5.0


def test_effort_regulation_slows_a_heavy_robot() -> None:
    p = HumanParams()
    light = SimulatedHuman(p, quick_task())
    heavy = SimulatedHuman(p, quick_task())
    run(light, PointRobot(START), 60.0)
    run(heavy, PointRobot(START, b=300.0), 120.0)
    assert light.finish_time is not None and heavy.finish_time is not None
    assert heavy.finish_time > light.finish_time + 1.0


def test_loop_mode_never_finishes() -> None:
    human = SimulatedHuman(HumanParams(), quick_task(), loop=True)
    trace = run(human, PointRobot(START), 40.0)
    assert not any(a.done for _, a in trace) and human.finish_time is None
    assert sum(1 for _, a in trace if a.phase is Phase.REACH) * DT > 5.0


def test_switch_policy_delay_and_hysteresis() -> None:
    p = HumanParams(decision_delay=0.5, comfort_reach=0.9, near_distance=0.2)
    pol = SwitchPolicy(p)
    far, handle, base = np.array([0.0, 1.5, 1.0]), np.array([0.5, 0.0, 1.0]), np.zeros(3)
    assert pol.update(0.0, 0, far, handle, base, False) is None
    assert pol.update(0.49, 0, far, handle, base, False) is None
    assert pol.update(0.50, 0, far, handle, base, False) == "locomotion"
    assert pol.want == "locomotion"
    near = far + [0.1, 0.0, 0.0]
    assert pol.update(1.0, 0, far, near, base, False) is None
    assert pol.update(1.5, 0, far, near, base, False) == "manipulation"
    # still beyond comfortable reach, but this hole already had its locomotion phase
    for t in np.arange(1.6, 4.0, 0.1):
        assert pol.update(float(t), 0, far, near, base, False) is None
    # the next far hole gets one again
    assert pol.update(4.0, 1, far, handle, base, False) is None
    assert pol.update(4.5, 1, far, handle, base, False) == "locomotion"
    # a wish that disappears before the delay is forgotten
    pol2 = SwitchPolicy(p)
    assert pol2.update(0.0, 1, far, handle, base, False) is None
    assert pol2.update(0.3, 1, np.zeros(3), handle, base, False) is None
    assert pol2.update(0.6, 1, far, handle, base, False) is None


def test_stall_triggers_locomotion_request() -> None:
    p = HumanParams(decision_delay=0.2, stall_time=0.5)
    pol = SwitchPolicy(p)
    goal, handle, base = np.array([0.5, 0.3, 1.0]), np.array([0.5, 0.0, 1.0]), np.zeros(3)
    reqs = [pol.update(k * 0.01, 0, goal, handle, base, True) for k in range(100)]
    hits = [k for k, r in enumerate(reqs) if r is not None]
    assert reqs[hits[0]] == "locomotion"
    assert hits[0] * 0.01 >= 0.5 - 1e-9


def test_human_knows_no_mode() -> None:
    """Structural: nothing in the human's API carries the control approach."""
    forbidden = {"mode", "strategy", "approach", "controller"}
    for fn in (SimulatedHuman.__init__, SimulatedHuman.update, SwitchPolicy.__init__,
               SwitchPolicy.update):
        assert forbidden.isdisjoint(inspect.signature(fn).parameters)
    assert forbidden.isdisjoint(HandleObservation._fields)
    assert forbidden.isdisjoint(f.name for f in HumanParams.__dataclass_fields__.values())


def test_same_observations_same_actions() -> None:
    """Replaying an observed trajectory into a fresh human reproduces every action."""
    human = SimulatedHuman(HumanParams(), quick_task())
    robot = PointRobot(START)
    obs_log, act_log = [], []
    for k in range(6000):
        obs = HandleObservation(k * DT, robot.x.copy(), robot.v.copy(), np.zeros(3))
        act = human.update(obs)
        obs_log.append(obs)
        act_log.append(act)
        robot.step(act.force, DT)
    replay = SimulatedHuman(HumanParams(), quick_task())
    for obs, act in zip(obs_log, act_log):
        again = replay.update(obs)
        np.testing.assert_array_equal(again.force, act.force)
        assert (again.switch_request, again.phase, again.done) == (
            act.switch_request, act.phase, act.done)
    assert any(a.switch_request for a in act_log)  # the far hole triggers a request


def test_params_validation() -> None:
    with pytest.raises(ValueError, match="stiffness"):
        HumanParams(stiffness=0.0)
    with pytest.raises(ValueError, match="f_max"):
        HumanParams(f_comfort=50.0, f_max=40.0)
    with pytest.raises(ValueError):
        Task(())
