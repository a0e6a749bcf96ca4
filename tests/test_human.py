"""Simulated human: minimum-jerk profile, reaction delay, task completion, switch policy,
and no knowledge of the control approach."""

from __future__ import annotations

import inspect

import numpy as np
import pytest

from mmctl.sim.human import (
    QUICK_HOLES,
    WALL_FAMILY,
    HandleObservation,
    HumanAction,
    HumanParams,
    Phase,
    SimulatedHuman,
    SwitchPolicy,
    Task,
    WallFamily,
    draw_wall_layout,
    min_jerk,
    noise_seed,
    peg_in_hole_task,
    wall_task,
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


# --- the wall task, the layout family, the hold, the button press, the motor noise ---

FWD = np.array([1.0, 0.0, 0.0])


def test_wall_task_geometry() -> None:
    """Approach points on the wall plane (vertical, its normal against the peg), each
    bottom ``depth`` along the peg, the heights as given, w to the robot's left."""
    holes = ((0.0, 1.0), (0.4, 0.85), (-0.3, 1.25))
    task = wall_task(START, FWD, holes, standoff=0.1, depth=0.05)
    assert task.surface is not None
    point, normal = np.array(task.surface.point), np.array(task.surface.normal)
    np.testing.assert_allclose(normal, -FWD)  # out of the wall, toward the robot
    np.testing.assert_allclose(point, START + 0.1 * FWD)
    for h, (w, z) in zip(task.holes, holes):
        ap, bt = np.array(h.approach), np.array(h.bottom)
        assert (ap - point) @ normal == pytest.approx(0.0, abs=1e-12)  # on the wall plane
        np.testing.assert_allclose(bt - ap, 0.05 * FWD, atol=1e-12)  # along the normal
        assert ap[2] == pytest.approx(z)
        assert ap[1] - START[1] == pytest.approx(w)  # heading x: left is +y
    # a robot turned by 90 deg: the wall ahead of it, left is -x
    task = wall_task(START, [0.0, 1.0, 0.0], ((0.3, 1.1),), standoff=0.0)
    np.testing.assert_allclose(task.holes[0].approach, [START[0] - 0.3, START[1], 1.1], atol=1e-12)
    # a slightly tilted peg still gives a vertical wall; a peg pointing down cannot
    tilted = wall_task(START, [1.0, 0.0, 0.05], ((0.0, 1.0),), standoff=0.1)
    assert tilted.surface is not None and tilted.surface.normal[2] == 0.0
    with pytest.raises(ValueError, match="horizontal"):
        wall_task(START, DOWN, ((0.0, 1.0),), standoff=0.1)


def test_wall_layout_family_is_seeded() -> None:
    fam = WALL_FAMILY
    layouts = {seed: draw_wall_layout(seed, fam, handle_height=1.05) for seed in range(12)}
    for seed, lay in layouts.items():
        assert lay == draw_wall_layout(seed, fam, handle_height=1.05)  # deterministic
        assert fam.holes[0] <= len(lay) <= fam.holes[1]
        w = np.array([h[0] for h in lay])
        z = np.array([h[1] for h in lay])
        assert np.all((z >= fam.heights[0]) & (z <= fam.heights[1]))
        assert 1.05 in z  # one hole at the start handle's height
        assert fam.near_edge[0] <= w.min() and w.max() <= fam.far_edge[1]
        # spread beyond the arm's reach, holes apart along the wall
        assert w.max() > fam.far_edge[0] - (fam.far_edge[0] - fam.near_edge[1]) / 4
        assert np.diff(np.sort(w)).min() > 0.08
    # the family varies: counts, spreads, heights and orders differ across seeds
    assert len(set(layouts.values())) == len(layouts)
    assert len({len(v) for v in layouts.values()}) > 1
    # a layout does not depend on the handle height except for its one hole
    a, b = draw_wall_layout(3, fam, 1.0), draw_wall_layout(3, fam, 1.2)
    assert sum(x != y for x, y in zip(a, b)) == 1 and [x[0] for x in a] == [x[0] for x in b]
    with pytest.raises(ValueError, match="holes"):
        WallFamily(holes=(3, 2))


def _closed_loop(p: HumanParams, task: Task, button: bool = True, seed: int = 0,
                 t_max: float = 60.0) -> tuple[SimulatedHuman, list[tuple[float, HumanAction]]]:
    human = SimulatedHuman(p, task, noise_seed=seed, button=button)
    robot = PointRobot(START)
    out = []
    for k in range(int(t_max / DT)):
        act = human.update(HandleObservation(k * DT, robot.x, robot.v, np.zeros(3)))
        out.append((k * DT, act))
        if act.phase is Phase.DONE:
            break
        robot.step(act.force, DT)
    return human, out


def test_the_hold_follows_t_f_and_leaves_it_alone() -> None:
    task = quick_task()
    short, _ = _closed_loop(HumanParams(hold_time=0.0), task)
    held, trace = _closed_loop(HumanParams(hold_time=1.5), task)
    assert short.finish_time is not None and held.finish_time == short.finish_time
    assert held.hold_end == pytest.approx(held.finish_time + 1.5, abs=2 * DT)
    hold = [t for t, a in trace if a.phase is Phase.HOLD]
    assert hold and min(hold) >= held.finish_time - DT and trace[-1][1].phase is Phase.DONE
    assert all(a.done for t, a in trace if t >= held.finish_time)
    # the peg stays in: the handle is held at the last hole's bottom
    last = np.array(task.holes[-1].bottom)
    assert all(np.linalg.norm(a.force) < 10.0 for t, a in trace if t in hold)
    assert short.hold_end is None and last.shape == (3,)


def test_the_button_press_costs_time_only_with_a_button() -> None:
    task = quick_task()  # one hole beyond the comfortable reach: one press there
    none, trace_none = _closed_loop(HumanParams(), task, button=False)
    free, _ = _closed_loop(HumanParams(press_time=0.0), task, button=True)
    slow, trace = _closed_loop(HumanParams(press_time=0.5), task, button=True)
    assert none.presses == 0 and not any(a.switch_request for _, a in trace_none)
    assert all(a.phase is not Phase.PRESS for _, a in trace_none)
    assert slow.presses == free.presses >= 2  # to locomotion and back
    pressing = [t for t, a in trace if a.phase is Phase.PRESS]
    assert len(pressing) * DT == pytest.approx(slow.presses * 0.5, abs=slow.presses * 2 * DT)
    # the request goes out when the press ends
    sent = [t for t, a in trace if a.switch_request]
    assert len(sent) == slow.presses and all(t > min(pressing) for t in sent)
    assert none.finish_time is not None and free.finish_time is not None
    assert slow.finish_time is not None and slow.finish_time > free.finish_time + 0.5


def test_motor_noise_is_signal_dependent_and_seeded() -> None:
    """Same seed: the same noise whatever the person observes; the noise is
    cv ||f|| eta on every axis (none at rest); another seed, another stream."""
    task = quick_task()
    p = HumanParams(force_cv=0.05)
    quiet = HumanParams(force_cv=0.0)
    a, tr_a = _closed_loop(p, task, seed=11, t_max=8.0)
    _, tr_b = _closed_loop(p, task, seed=11, t_max=8.0, button=False)
    _, tr_c = _closed_loop(p, task, seed=12, t_max=8.0)
    def eta(tr: list[tuple[float, HumanAction]]) -> np.ndarray:
        return np.array([x.noise for _, x in tr])

    n = min(len(tr_a), len(tr_b))
    np.testing.assert_array_equal(eta(tr_a)[:n], eta(tr_b)[:n])
    assert np.abs(eta(tr_a)[:n] - eta(tr_c)[:n]).max() > 0.5
    e = eta(tr_a)
    assert 0.7 < e.std() < 1.3  # unit variance (per axis)
    # replay the noisy run's observations into a noise-free twin: the difference is
    # cv ||f|| eta
    noisy = SimulatedHuman(p, task, noise_seed=11)
    clean = SimulatedHuman(quiet, task, noise_seed=11)
    robot = PointRobot(START)
    for k in range(3000):
        obs = HandleObservation(k * DT, robot.x.copy(), robot.v.copy(), np.zeros(3))
        fa, fb = noisy.update(obs), clean.update(obs)
        mag = float(np.linalg.norm(fb.force))
        assert fa.noise is not None
        np.testing.assert_allclose(fa.force - fb.force, 0.05 * mag * fa.noise, atol=1e-9)
        if mag == 0.0:
            np.testing.assert_array_equal(fa.force, 0.0)
        robot.step(fa.force, DT)
    assert a.finish_time is None  # 8 s: still working (the check above ran mid-task)


def test_noise_seed_is_per_user_not_per_approach() -> None:
    s = noise_seed(4, 2)
    assert s.entropy == noise_seed(4, 2).entropy and s.spawn_key == noise_seed(4, 2).spawn_key
    g1, g2, g3 = (np.random.default_rng(x) for x in (noise_seed(4, 2), noise_seed(4, 2),
                                                       noise_seed(4, 3)))
    r1, r2, r3 = g1.standard_normal(5), g2.standard_normal(5), g3.standard_normal(5)
    np.testing.assert_array_equal(r1, r2)
    assert not np.allclose(r1, r3)
    # apart from the user's parameters' stream SeedSequence([seed, user])
    user = np.random.default_rng(np.random.SeedSequence([4, 2])).standard_normal(5)
    assert not np.allclose(r1, user)
