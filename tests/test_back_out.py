"""Every limit can be backed out of (issue 29, point 3).

The robot starts at rest at each limit the controller brakes at, and just beyond it
where that is allowed: a joint's position margin, the singularity braking's condition
number, a virtual wall, the self-collision margin (and an ISO cap lowered at speed: its
own test, last).  Twelve pushes are tried (30 N along each axis of the handle's frame
both ways, 3 N m about each): in every case the first cycle's command

* never takes the robot deeper (the limit's own measure does not fall along it), and
* some push takes it out at once (the measure rises along that cycle's command, and
  over 50 ms of it on the simulated plant),

with no fault.  The measure is each limit's distance: the joint's room to its margin
[rad], 1/sqrt(cond) less the braking's stop [1], the handle's height over the wall [m],
the nearest parts' distance less the margin [m].  Through the running daemon:
tests/test_back_out_daemon.py (the collision margin, then the reduced profile at speed).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from mmctl.config import config_from_dict, default_config
from mmctl.control.step import Controller, StepInputs
from mmctl.model.geometry import BodyModel
from mmctl.sim.plant import Plant

T = 0.002
H = 1e-3  # [s] of the first command: the measure's change along it
PUSHES = [np.r_[s * 30.0 * e, np.zeros(3)] for e in np.eye(3) for s in (1.0, -1.0)] + \
         [np.r_[np.zeros(3), s * 3.0 * e] for e in np.eye(3) for s in (1.0, -1.0)]


def _bisect(f: Callable[[float], float], lo: float, hi: float, target: float) -> float:
    """x in [lo, hi] with f(x) = target (f monotone between them)."""
    f_lo = f(lo) - target
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if (f(mid) - target) * f_lo > 0:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


def _first_cycle(ctl: Controller, q: np.ndarray, push: np.ndarray,
                 measure: Callable[[np.ndarray], float]) -> float:
    """The limit's measure's rate along the first command from rest under ``push``."""
    _, out = ctl.step(ctl.initial_state("min-energy"), StepInputs(push, q, np.zeros(9), T))
    assert out.fault is None, out.fault
    return (measure(q + H * out.qdot) - measure(q)) / H


def _joint(ctl: Controller, beyond: float) -> tuple[np.ndarray, Callable[[np.ndarray], float]]:
    """The shoulder's pan at its upper position margin (``beyond`` past it [rad]): the
    arm otherwise at q_des (the elbow's own limit folds it into itself)."""
    lim = ctl.cfg.limits
    top = lim.joint_position_max[0] - lim.position_margin
    q = np.r_[ctl.q_des[:6], 0.0, 0.0, 0.0]
    q[0] = top + beyond
    return q, lambda x: top - float(x[0])


#: tests/test_singularity_braking.py's start: wrist 2 0.35 rad from a singular pose
#: where the base's yaw cannot stand in for the lost rotation (the preferred pose too)
SINGULAR_START = [0.107465, -3.078638, 2.334328, 0.717837, 0.35, -2.081822]


def _singular(beyond: float) -> tuple[Controller, np.ndarray, Callable[[np.ndarray], float]]:
    """Wrist 2 turned toward the singular pose until cond = the braking's stop (times
    ``1 + beyond``: past the stop, short of the fault)."""
    ctl = Controller(config_from_dict({"robot": {"q_des": SINGULAR_START}}))
    q = np.r_[SINGULAR_START, 0.0, 0.0, 0.0]

    def r(x: np.ndarray) -> float:
        return 1.0 / math.sqrt(ctl.model.condition(x))

    def at(w: float) -> np.ndarray:
        x = q.copy()
        x[4] = w
        return x

    r_stop = 1.0 / math.sqrt(ctl.cond_stop * (1.0 + beyond))
    q = at(_bisect(lambda w: r(at(w)), q[4], 0.0, r_stop))
    return ctl, q, lambda x: r(x) - ctl.r_stop


def _wall(beyond: float) -> tuple[Controller, np.ndarray, Callable[[np.ndarray], float]]:
    """A floor for the handle 0.1 m under its height at q_des; the handle lowered onto
    it (``beyond`` below it [m])."""
    probe = Controller(default_config())
    q = np.r_[probe.q_des[:6], 0.0, 0.0, 0.0]
    floor = float(probe.model.fk_base(q, "tool").translation[2]) - 0.1
    ctl = Controller(config_from_dict({"walls": {"ee_box": [[-2.0, -2.0, floor],
                                                            [2.0, 2.0, 2.0]]}}))

    def z(x: float) -> float:
        y = q.copy()
        y[1] += x
        return float(ctl.model.fk_base(y, "tool").translation[2])

    q[1] += _bisect(z, 0.0, 0.5, floor - beyond)
    return ctl, q, lambda x: float(ctl.model.fk_base(x, "tool").translation[2]) - floor


def _collision(ctl: Controller, beyond: float
               ) -> tuple[np.ndarray, Callable[[np.ndarray], float]]:
    """The handle lowered onto the deck until the distance is the margin (less
    ``beyond`` [m], within the tolerance)."""
    body = BodyModel(ctl.cfg.robot, ctl.model.arm, ctl.model.mount)
    margin = ctl.cfg.safety.collision_margin
    q = np.r_[ctl.q_des[:6], 0.0, 0.0, 0.0]

    def at(x: float) -> np.ndarray:
        y = q.copy()
        y[1] += x
        return y

    x = _bisect(lambda x: body.clearance(at(x)[:6]), 0.0, 1.2, margin - beyond)
    return at(x), lambda y: body.clearance(y[:6]) - margin


def _check(ctl: Controller, q: np.ndarray, measure: Callable[[np.ndarray], float]) -> None:
    rates = [_first_cycle(ctl, q, push, measure) for push in PUSHES]
    assert min(rates) > -1e-6, rates  # no push goes deeper (1 um/s: rounding)
    best = int(np.argmax(rates))
    assert rates[best] > 1e-9, rates  # one goes out at once
    # ... and keeps going: 50 ms of it on the simulated plant
    plant = Plant(ctl.cfg, q)
    state = ctl.initial_state("min-energy")
    for _ in range(25):
        x, xd = plant.state()
        state, out = ctl.step(state, StepInputs(PUSHES[best], x, xd, T))
        assert out.fault is None
        plant.step(out.qdot_arm, out.base_twist, T)
    assert measure(plant.state().q) > measure(q) + 1e-4, (measure(q), measure(plant.state().q))


@pytest.mark.parametrize("beyond", [0.0, 0.01])
def test_a_joint_at_or_past_its_margin(beyond: float) -> None:
    ctl = Controller(default_config())
    q, measure = _joint(ctl, beyond)
    _check(ctl, q, measure)


@pytest.mark.parametrize("beyond", [0.0, 0.5])
def test_at_or_past_the_singularity_brakes_stop(beyond: float) -> None:
    ctl, q, measure = _singular(beyond)
    assert ctl.model.condition(q) < ctl.max_condition  # short of the fault
    _check(ctl, q, measure)


@pytest.mark.parametrize("beyond", [0.0, 0.003])
def test_on_or_below_a_walls_floor(beyond: float) -> None:
    ctl, q, measure = _wall(beyond)
    _check(ctl, q, measure)


@pytest.mark.parametrize("beyond", [0.0, 0.01])
def test_at_or_inside_the_collision_margin(beyond: float) -> None:
    ctl = Controller(default_config())
    q, measure = _collision(ctl, beyond)
    _check(ctl, q, measure)


def test_over_an_iso_cap_the_reduced_profile_switched_on_at_speed() -> None:
    """The end-effector at the normal cap (> 0.4 m/s), then the reduced profile (0.25
    m/s): the robot is over its cap.  The measure is the cap less the end-effector's
    speed [m/s].  Every push, along the motion too, slows it in the first cycle (the
    command heads for the new cap on the acceleration limits: nothing can go deeper),
    every cycle after is within the acceleration limits, and the speed comes down to
    the cap under a push along the motion, with no fault."""
    ctl = Controller(default_config())
    q0 = np.r_[ctl.q_des[:6], 0.0, 0.0, 0.0]
    plant = Plant(ctl.cfg, q0)
    state = ctl.initial_state("min-energy")
    along = np.array([0.0, 80.0, 0.0, 0.0, 0.0, 0.0])
    for _ in range(500):
        x, xd = plant.state()
        state, out = ctl.step(state, StepInputs(along, x, xd, T))
        assert out.fault is None
        plant.step(out.qdot_arm, out.base_twist, T)
    state = ctl.set_profile(state, "reduced")
    x, xd = plant.state()
    J = ctl.model.update(x).J

    def ee(qdot: np.ndarray) -> float:
        return float(np.linalg.norm((J @ qdot)[:3]))

    cap = ctl.cfg.limits.reduced_ee_speed
    before = ee(state.qdot)
    assert before > cap + 0.15, before  # over the cap by more than half of it
    first = {}
    for push in [*PUSHES, along, -along]:
        _, out = ctl.step(state, StepInputs(push, x, xd, T))
        assert out.fault is None, out.fault
        first[tuple(push)] = ee(out.qdot)
    assert max(first.values()) < before - 1e-4, (before, first)  # all out at once
    lim = ctl.cfg.limits
    acc = np.r_[lim.joint_acceleration, [lim.base_linear_acceleration] * 2,
                lim.base_angular_acceleration] * T
    prev = state.qdot
    for k in range(500):  # pushed along: down to the cap on the acceleration limits
        x, xd = plant.state()
        state, out = ctl.step(state, StepInputs(along, x, xd, T))
        assert out.fault is None
        assert np.all(np.abs(out.qdot - prev) <= acc * (1 + 1e-9)), k
        prev = out.qdot
        plant.step(out.qdot_arm, out.base_twist, T)
    assert float(np.linalg.norm((ctl.model.update(x).J @ prev)[:3])) <= cap * (1 + 1e-9)
