"""Whole-body caps for hand guiding (issue 18, point 2): kinetic energy, base speed and
end-effector speed from ISO/TS 15066's transient-contact values, applied by scaling the
whole command (direction kept), the reduced profile, and their effect on the simulated
robot's plant under hard pushes."""

from __future__ import annotations

import math
from typing import get_args

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mmctl.bench.caps import exceeded, run_pushes
from mmctl.config import config_from_dict, default_config
from mmctl.config.control import BodyRegionName
from mmctl.control.energy import kinetic_energy
from mmctl.control.iso15066 import BODY_REGIONS, derive, reduced_mass
from mmctl.control.step import Controller, StepInputs, whole_body_caps
from mmctl.model import RobotModel

CFG = default_config()
CTL = Controller(CFG)
MODEL = CTL.model
T = 0.002


def test_the_config_offers_exactly_the_regions_with_values() -> None:
    assert set(get_args(BodyRegionName)) == {"none", *BODY_REGIONS}


def test_chest_values_follow_iso_ts_15066_annex_a() -> None:
    """F_T = 2 x 140 N, k = 25 N/mm, m_H = 40 kg: E = F^2 / (2k), v = F / sqrt(mu k)."""
    robot = CFG.robot.base_mass + MODEL.arm_mass + CFG.sensor.wrench.handle_mass
    caps = derive("chest", robot, MODEL.arm_mass, CFG.sensor.wrench.handle_mass)
    assert caps.energy == pytest.approx(280.0 ** 2 / (2 * 25_000.0))  # 1.568 J
    mu = 1.0 / (1.0 / 40.0 + 1.0 / robot)
    assert caps.base_speed == pytest.approx(280.0 / math.sqrt(mu * 25_000.0))
    assert 0.30 < caps.base_speed < 0.33  # the base's mass dominates mu
    m_r = MODEL.arm_mass / 2 + CFG.sensor.wrench.handle_mass
    assert caps.ee_speed == pytest.approx(280.0 / math.sqrt(reduced_mass(40.0, m_r) * 25e3))
    assert whole_body_caps(CFG, MODEL.arm_mass) == caps  # the default region: chest
    none = config_from_dict({"limits": {"body_region": "none"}})
    assert math.isinf(whole_body_caps(none, MODEL.arm_mass).energy)


def test_explicit_caps_win_over_the_region() -> None:
    cfg = config_from_dict({"limits": {"energy": 0.5, "base_speed": 0.2}})
    caps = whole_body_caps(cfg, MODEL.arm_mass)
    assert caps.energy == 0.5 and caps.base_speed == 0.2
    assert caps.ee_speed == whole_body_caps(CFG, MODEL.arm_mass).ee_speed


vec9 = st.lists(st.floats(-5.0, 5.0), min_size=9, max_size=9)


@settings(max_examples=300, deadline=None)
@given(vec9, st.integers(0, 2**32 - 1))
def test_every_cap_holds_and_the_direction_is_kept(qd: list[float], seed: int) -> None:
    rng = np.random.default_rng(seed)
    q = np.concatenate((np.asarray(CFG.robot.q_des) + rng.uniform(-0.5, 0.5, 6),
                        rng.uniform(-2, 2, 3)))
    kin = MODEL.update(q)
    lim = CTL.limits
    want = np.array(qd)
    # from motion within the caps (a cycle's steady state), and from rest
    prev = lim.apply(0.5 * want, np.zeros(9), q, kin.J, 1.0, kin.M_a, kin.M_b).qdot
    for start in (prev, np.zeros(9)):
        res = lim.apply(want, start, q, kin.J, T, kin.M_a, kin.M_b)
        x = res.qdot
        assert kinetic_energy(kin.M_a, kin.M_b, x).total <= lim.energy * (1 + 1e-9)
        assert math.hypot(x[6], x[7]) <= lim.v_lin * (1 + 1e-9)
        assert np.linalg.norm((kin.J @ x)[:3]) <= lim.ee_lin * (1 + 1e-9)
    res = lim.apply(want, np.zeros(9), q, kin.J, 1.0, kin.M_a, kin.M_b)  # no accel. limit
    assert np.allclose(res.qdot, res.scale * want, atol=1e-12)  # direction kept


def test_the_binding_cap_is_named() -> None:
    q = np.concatenate((np.asarray(CFG.robot.q_des), np.zeros(3)))
    kin = MODEL.update(q)
    lim = CTL.limits
    base = np.zeros(9)
    base[6] = 0.25  # 0.25 m/s: under the base speed cap, E = 1/2 115 0.25^2 = 3.6 J
    res = lim.apply(base, np.zeros(9), q, kin.J, 1.0, kin.M_a, kin.M_b)
    assert res.limit == "energy"
    assert kinetic_energy(kin.M_a, kin.M_b, res.qdot).total == pytest.approx(lim.energy)
    slow = 0.1 * base
    assert lim.apply(slow, np.zeros(9), q, kin.J, 1.0, kin.M_a, kin.M_b).limit == ""
    assert lim.apply(slow, np.zeros(9), q, kin.J, T, kin.M_a, kin.M_b).limit == "acceleration"


@pytest.mark.parametrize("mode, profile", [("min-energy", "normal"),
                                           ("locomotion", "normal"),
                                           ("manipulation", "reduced")])
def test_hard_pushes_on_the_simulated_plant_stay_within_the_caps(mode: str,
                                                                 profile: str) -> None:
    """80 N pushes (far beyond the caps) on the simulated robot's own plant: the actual
    E_K, base and end-effector speeds stay within their caps (3 % for the one cycle the
    arm and the drives lag behind a command), and the caps are what bound the motion:
    the same pushes without them (and in the normal profile) go well past."""
    r = run_pushes(CFG, mode, profile, 80.0, 1.5)
    assert exceeded(r, 0.03) == [], r
    assert set(r["binding"]) & {"energy", "ee_speed"}, r["binding"]
    uncapped = run_pushes(config_from_dict({"limits": {"body_region": "none"}}),
                          mode, "normal", 80.0, 1.5)
    over = [k for k in ("energy_J", "ee_speed_m_s")
            if uncapped[k]["max"] > 1.2 * r[k]["cap"]]
    assert over, uncapped


def test_the_reduced_profile_mid_motion_brakes_on_the_acceleration_limits() -> None:
    """Switched to reduced at full speed: no jump (every change within the acceleration
    limits), and the end-effector is at 0.25 m/s at most once the braking is over."""
    from mmctl.sim.plant import Plant

    lim = CFG.limits
    acc = np.r_[lim.joint_acceleration, [lim.base_linear_acceleration] * 2,
                lim.base_angular_acceleration] * T
    state = CTL.initial_state("manipulation")
    q0 = np.concatenate((np.asarray(CFG.robot.q_des), np.zeros(3)))
    plant = Plant(CFG, q0)
    push = np.array([0.0, 80.0, 0.0, 0.0, 0.0, 0.0])
    prev = np.zeros(9)
    for k in range(1500):
        q, qd = plant.state()
        if k == 500:
            state = CTL.set_profile(state, "reduced")
            ee_before = float(np.linalg.norm((MODEL.update(q).J @ qd)[:3]))
            assert ee_before > 0.4  # moving fast: the normal caps
        state, out = CTL.step(state, StepInputs(push, q, qd, T))
        assert np.all(np.abs(out.qdot - prev) <= acc * (1 + 1e-9)), k
        prev = out.qdot
        plant.step(out.qdot_arm, out.base_twist, T)
    q, qd = plant.state()
    assert np.linalg.norm((MODEL.update(q).J @ qd)[:3]) <= 0.25 * 1.03
    assert state.reduced and CTL.set_profile(state, "normal").reduced is False
    with pytest.raises(ValueError, match="unknown profile 'fast'"):
        CTL.set_profile(state, "fast")


def test_the_profile_survives_an_enable() -> None:
    from mmctl.control.cycle import CycleChain

    chain = CycleChain(CFG)
    s = chain.initial_state()
    s = s._replace(controller=chain.controller.set_profile(s.controller, "reduced"))
    assert chain.at_rest(s).controller.reduced
    assert CycleChain(config_from_dict({"limits": {"profile": "reduced"}})
                      ).initial_state().controller.reduced
    assert RobotModel  # the model the caps' masses come from
