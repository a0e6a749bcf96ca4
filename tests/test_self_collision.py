"""Self-collision avoidance (control/body.py): pushes toward the robot's own body stop at
``safety.collision_margin``; moving apart is free, also from inside the margin; deeper
than its tolerance is the ``self_collision`` fault, and enabling there is refused.
Closed loop on the simulated robot's own plant, as tests/test_walls.py."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from mmctl.config import config_from_dict, default_config
from mmctl.control.body import BodyCheck
from mmctl.control.cycle import CycleChain
from mmctl.control.step import Controller, StepInputs
from mmctl.errors import FaultCause
from mmctl.model.geometry import BodyModel
from mmctl.model.planar import world_to_base
from mmctl.sim.plant import Plant

T = 0.002
MARGIN = 0.05  # safety.collision_margin's default
#: [m] the target: pushes stop with the distance at the margin +- 5 mm
BAND = 0.005


def _push(ctl: Controller, force: list[float], seconds: float, mode: str,
          q0: np.ndarray | None = None) -> tuple[list[Any], list[float], Plant]:
    """The person pushes the handle with ``force`` (world) for ``seconds``: every
    cycle's output, the smallest distance of the robot's parts at every 5th cycle, and
    the plant."""
    body = BodyModel(ctl.cfg.robot, ctl.model.arm, ctl.model.mount)
    start = np.concatenate((ctl.q_des[:6], np.zeros(3))) if q0 is None else q0
    plant = Plant(ctl.cfg, start)
    state = ctl.initial_state(mode)
    outs, dists = [], []
    for k in range(int(seconds / T)):
        q, qd = plant.state()
        f_h = np.concatenate((world_to_base(force, float(q[8])), np.zeros(3)))
        state, out = ctl.step(state, StepInputs(f_h, q, qd, T))
        assert out.fault is None, (out.fault, out.body)
        outs.append(out)
        if k % 5 == 0:
            dists.append(body.closest(q[:6]).distance)
        plant.step(out.qdot_arm, out.base_twist, T)
    dists.append(body.closest(plant.state().q[:6]).distance)
    return outs, dists, plant


@pytest.mark.parametrize(("mode", "force", "pair"), [
    ("min-energy", [0.0, 0.0, -80.0], ("deck", "handle")),
    ("min-energy", [-80.0, 0.0, 0.0], ("forearm", "handle")),
    ("manipulation", [-60.0, 0.0, -60.0], ("upper_arm", "handle")),
    # the upper arm turning down about the shoulder onto the deck: its end's distance
    # stands still while its side closes (what the look-ahead is for)
    ("manipulation", [-80.0, 0.0, -40.0], ("deck", "upper_arm")),
    ("min-energy", [80.0, 80.0, -40.0], ("deck", "upper_arm")),
    ("manipulation", [0.0, 0.0, -30.0], ("deck", "handle")),
])
def test_a_push_into_the_robots_own_body_stops_at_the_margin(
        mode: str, force: list[float], pair: tuple[str, str]) -> None:
    ctl = Controller(default_config())
    outs, dists, _ = _push(ctl, force, 4.0, mode)
    assert MARGIN - BAND < min(dists) < MARGIN + BAND, min(dists)  # got there
    assert "self_collision" in {o.limit for o in outs}
    bound = [o.body[0] for o in outs if o.limit == "self_collision" and o.body is not None]
    assert pair in bound  # status names the pair that binds
    # without the check the same push goes into the body
    off = Controller(config_from_dict({"safety": {"collision_check": False}}))
    _, dists_off, _ = _push(off, force, 4.0, mode)
    assert min(dists_off) < MARGIN - 0.02, min(dists_off)


def test_many_random_pushes_never_go_inside_the_margin() -> None:
    """Seeded random pushes of 30-80 N in random directions, in every mode, each from
    where the last left the robot (`tools/self_collision_soak.py` runs many more)."""
    rng = np.random.default_rng(2929)
    ctl = Controller(default_config())
    lowest = np.inf
    q0 = None
    for i in range(8):
        mode = ("min-energy", "manipulation", "locomotion", "switch")[i % 4]
        direction = rng.normal(size=3)
        direction[2] = -abs(direction[2])  # toward the deck half the time at least
        force = (rng.uniform(30.0, 80.0) * direction / np.linalg.norm(direction)).tolist()
        _, dists, plant = _push(ctl, force, 1.5, mode, q0)
        lowest = min(lowest, min(dists))
        q0 = plant.state().q.copy()
    assert lowest > MARGIN - BAND, lowest


def _deck_pose(ctl: Controller, distance: float) -> np.ndarray:
    """q (9,): q_des with the handle lowered (shoulder lift) until the deck-handle
    distance is ``distance`` [m] (bisection on the model's own distance)."""
    body = BodyModel(ctl.cfg.robot, ctl.model.arm, ctl.model.mount)
    lo, hi = 0.0, 1.2  # shoulder lift change [rad]: 0 is far, 1.2 is through the deck
    q = np.concatenate((ctl.q_des[:6], np.zeros(3)))

    def d(x: float) -> float:
        qq = q.copy()
        qq[1] += x
        return {p.pair: p.distance for p in body.distances(qq[:6])}[("deck", "handle")]

    assert d(lo) > distance > d(hi)
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if d(mid) > distance else (lo, mid)
    q[1] += lo
    return q


@pytest.mark.parametrize("depth", [0.0, 0.01])
def test_inside_the_margin_a_pull_out_moves_at_once_and_a_push_in_does_not(
        depth: float) -> None:
    """At the margin, or 1 cm inside it (within the tolerance), at rest: no fault; the
    first cycle of a pull along the contact's normal (away from the deck) already
    opens the distance, and the push the other way gives no motion that closes it.
    (The handle hangs in front of the deck's edge at this pose, tilted toward the
    base: "up" is not "away" there, the normal is.)"""
    cfg = default_config()
    ctl = Controller(cfg)
    check = BodyCheck(cfg, ctl.model)
    body = BodyModel(cfg.robot, ctl.model.arm, ctl.model.mount)
    q = _deck_pose(ctl, MARGIN - depth)
    contact = {d.pair: d for d in body.distances(q[:6])}[("deck", "handle")]
    normal = np.subtract(contact.p2, contact.p1)
    normal /= np.linalg.norm(normal)  # from the deck to the handle (base = world here)
    grad = np.asarray({n.pair: n for n in check.near(q[:6])[0]}[("deck", "handle")].grad)
    for sign in (1.0, -1.0):
        state = ctl.initial_state("min-energy")
        f_h = np.concatenate((40.0 * sign * normal, np.zeros(3)))
        state, out = ctl.step(state, StepInputs(f_h, q, np.zeros(9), T))
        assert out.fault is None
        rate = float(grad.dot(out.qdot_arm))  # the distance's rate [m/s]
        if sign > 0:  # (from rest: one cycle of the acceleration limits)
            assert rate > 1e-5, (rate, out.limit)
        else:
            assert rate <= 1e-12, (rate, out.limit)


def test_deeper_than_the_tolerance_is_a_fault_and_enabling_is_refused() -> None:
    cfg = default_config()
    ctl = Controller(cfg)
    q = _deck_pose(ctl, MARGIN - cfg.safety.collision_tolerance - 0.005)
    _, out = ctl.step(ctl.initial_state("min-energy"),
                      StepInputs(np.zeros(6), q, np.zeros(9), T))
    assert out.fault is FaultCause.SELF_COLLISION
    assert out.body is not None and out.body[0] == ("deck", "handle")
    # disarmed there: the cycle reports the condition, so `enable` is refused
    chain = CycleChain(cfg)
    assert chain.controller.body is not None
    inside = chain.controller.body.inside(q[:6])
    assert inside is not None and inside[0] == ("deck", "handle")
    assert chain.controller.body.inside(ctl.q_des[:6]) is None


def test_the_check_is_pure_the_same_inputs_give_the_same_commands() -> None:
    """coal keeps its last answer as its next start; the check does not (a fresh
    GeometryData each measure), so the update replays bit for bit."""
    ctl = Controller(default_config())
    q = _deck_pose(ctl, 0.06)
    f_h = np.array([0.0, 0.0, -40.0, 0.0, 0.0, 0.0])
    s = ctl.initial_state("min-energy")
    s1, a = ctl.step(s, StepInputs(f_h, q, np.zeros(9), T))
    ctl.step(s, StepInputs(f_h, q + 0.3, np.zeros(9), T))  # something else between
    s2, b = ctl.step(s, StepInputs(f_h, q, np.zeros(9), T))
    assert np.array_equal(a.qdot, b.qdot) and a.body == b.body and s1.body == s2.body


def test_a_preferred_pose_inside_the_margin_is_refused_by_name() -> None:
    from mmctl.errors import ConfigError

    with pytest.raises(ConfigError) as err:
        Controller(config_from_dict({"robot": {"q_des": [0.0, -1.57, 2.9, -1.0, 1.57, 0.0]}}))
    assert "robot.q_des" in str(err.value) and "collision_margin" in str(err.value)
