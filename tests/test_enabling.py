"""The enabling (hold-to-run) switch: released, the armed robot comes to rest on the
acceleration limits and stays still; held again, it starts from rest (no jump); two
contacts that disagree too long are a fault.  The controller and the update's reading
of the switch here; the daemon's cycle on scripted devices in ``test_fault_matrix.py``; the simulated
robot's own inputs through RTDE in ``test_sim_process.py``."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from mmctl.config import config_from_dict, default_config
from mmctl.control.cycle import CycleChain
from mmctl.control.step import Controller, StepInputs
from mmctl.control.update import Readings, Update, UpdateState
from mmctl.errors import ConfigError, FaultCause
from mmctl.types import ArmState

T = 0.002
PUSH = np.array([25.0, 10.0, 0.0, 0.0, 0.0, 0.0])  # [N] a firm push: arm and base move


def _plant(q: np.ndarray, qdot: np.ndarray) -> np.ndarray:
    out = q + T * qdot
    c, s = math.cos(q[8]), math.sin(q[8])
    out[6] = q[6] + T * (c * qdot[6] - s * qdot[7])
    out[7] = q[7] + T * (s * qdot[6] + c * qdot[7])
    return out


@pytest.mark.parametrize("mode", ["min-energy", "locomotion", "manipulation"])
def test_released_the_robot_comes_to_rest_on_the_limits_and_starts_again_from_rest(
        mode: str) -> None:
    cfg = default_config()
    ctl = Controller(cfg)
    lim = cfg.limits
    acc = np.r_[lim.joint_acceleration, [lim.base_linear_acceleration] * 2,
                lim.base_angular_acceleration] * T
    state = ctl.initial_state(mode)
    q, qdot = ctl.q_des.copy(), np.zeros(9)
    for _ in range(500):  # 1 s pushed: moving
        state, out = ctl.step(state, StepInputs(PUSH, q, qdot, T))
        q, qdot = _plant(q, out.qdot), out.qdot.copy()
    moving = out.qdot.copy()
    assert np.linalg.norm(moving) > 0.05
    # released, the person still pushing: the command decelerates, never accelerates
    prev = moving
    n_rest = None
    for k in range(1000):
        state, out = ctl.step(state, StepInputs(PUSH, q, qdot, T, hold=True))
        q, qdot = _plant(q, out.qdot), out.qdot.copy()
        assert np.all(np.abs(out.qdot) <= np.abs(prev) + 1e-12)  # every speed falls
        assert np.all(np.abs(out.qdot - prev) <= acc * (1 + 1e-9))  # within the limits
        assert np.all(out.v_d == 0.0) and np.all(state.v == 0.0)  # no admittance wind-up
        prev = out.qdot
        if n_rest is None and not out.qdot.any():
            n_rest = k + 1
    assert n_rest is not None
    # at rest no later than the slowest coordinate at its own acceleration limit
    bound = max(*(np.abs(moving[:6]) / acc[:6]),
                math.hypot(moving[6], moving[7]) / acc[6],  # |a_xy| is limited as a whole
                abs(moving[8]) / acc[8]) + 1
    assert n_rest <= math.ceil(bound), (n_rest, bound)
    assert not out.qdot.any()  # and stays there, pushed or not
    # held again: from rest, within the acceleration limits (no jump)
    state, out = ctl.step(state, StepInputs(PUSH, q, np.zeros(9), T))
    assert np.linalg.norm(out.qdot) > 0
    assert np.all(np.abs(out.qdot) <= acc * (1 + 1e-9))


def _enabling(inputs: tuple[int, ...], active_low: bool = False) -> tuple[Update, UpdateState]:
    cfg = config_from_dict({"enabling": {"inputs": list(inputs), "active_low": active_low,
                                         "discrepancy_time": 0.05}})
    update = Update(cfg, CycleChain(cfg))
    return update, update.initial_state()


def _read(update: Update, s: UpdateState, bits: int, now: float
          ) -> tuple[UpdateState, bool, dict[FaultCause, Any]]:
    """The update's enabling part on one arm sample's inputs: (state, held, conditions)."""
    conditions: dict[FaultCause, Any] = {}
    arm = ArmState(np.zeros(6), np.zeros(6), now, 2, 1)
    r = Readings(0, now, T, arm, None, None, bits)
    s, held = update._enabling(s, r, conditions)
    return s, held, conditions


def test_one_contact_and_its_polarity() -> None:
    up, s = _enabling((17,))
    s, held, _ = _read(up, s, 0, 0.0)
    assert held is False and s.enabling.held is False
    s, held, _ = _read(up, s, 1 << 17, 0.1)
    assert held is True and s.enabling.held is True
    low, ls = _enabling((17,), active_low=True)
    assert _read(low, ls, 1 << 17, 0.2)[1] is False
    assert _read(low, ls, 0, 0.3)[1] is True


def test_two_contacts_must_agree_within_the_discrepancy_time() -> None:
    up, s = _enabling((8, 9))
    s, held, c = _read(up, s, 1 << 8, 1.0)  # the first closes, the second follows in 50 ms
    assert held is False and s.enabling.held is None and not c
    s, held, c = _read(up, s, 1 << 8, 1.04)
    assert held is False and not c
    s, held, c = _read(up, s, (1 << 8) | (1 << 9), 1.045)
    assert held is True and not c
    s, held, c = _read(up, s, 1 << 8, 2.0)  # a broken wire on the second channel
    assert held is False and not c
    s, held, c = _read(up, s, 1 << 8, 2.05)  # 50 ms: still within the time
    assert not c
    s, held, c = _read(up, s, 1 << 8, 2.0501)
    assert held is False and set(c) == {FaultCause.ENABLING_DEVICE}
    assert c[FaultCause.ENABLING_DEVICE]["inputs"] == [8, 9]
    assert c[FaultCause.ENABLING_DEVICE]["levels"] == [1, 0]
    s, held, c = _read(up, s, 1 << 8, 3.0)  # as long as they disagree
    assert FaultCause.ENABLING_DEVICE in c
    s, held, c = _read(up, s, 0, 3.1)  # both released: agree again
    assert held is False and s.enabling.held is False and not c


@pytest.mark.parametrize("bad, message", [
    ({"inputs": [8, 8]}, "must be two different inputs"),
    ({"inputs": [1, 2, 3]}, "at most 2 inputs"),
    ({"inputs": [18]}, "must be >= 0 and <= 17"),
    ({"discrepancy_time": 5.0}, "must be >= 0.002 and <= 1.0"),
])
def test_bad_enabling_config_names_the_key(bad: dict[str, object], message: str) -> None:
    with pytest.raises(ConfigError, match=message) as err:
        config_from_dict({"enabling": bad})
    assert "enabling." in str(err.value)


def test_the_switch_mode_button_cannot_be_an_enabling_contact() -> None:
    with pytest.raises(ConfigError, match="must not include daemon.switch_input = 16"):
        config_from_dict({"enabling": {"inputs": [16]}, "daemon": {"switch_input": 16}})
