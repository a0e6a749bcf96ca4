"""Run-time parameter changes (`mmctl set`): validated as the configuration is, and
installed in the running chain without a jump in the commanded velocity."""

from __future__ import annotations

import time

import numpy as np
import pytest

from mmctl.config import Config, config_from_dict, default_config
from mmctl.config.schema import keys
from mmctl.control.params import SETTABLE, get_value, with_value
from mmctl.errors import MmctlError
from mmctl.runtime.core import ControlCore
from mmctl.types import ArmState, Odometry, Wrench

T = 0.002


def test_every_settable_key_exists_and_round_trips() -> None:
    cfg = default_config()
    known = {k for k, *_ in keys(Config)}
    for key in SETTABLE:
        assert key in known, key
        assert with_value(cfg, key, get_value(cfg, key)) == cfg, key


@pytest.mark.parametrize(("key", "value", "message"), [
    ("admittance.damping", -5, "admittance.damping[0] = -5.0: must be >= 1.0"),
    ("admittance.mass", [1, 2], "expected a list of 6 numbers, got 2"),
    ("limits.ee_speed", 30, "limits.ee_speed = 30"),
    ("limits.body_region", "elbow", "must be one of"),
    ("loop.rate_hz", 250, "cannot change while the daemon runs"),
    ("admittance.dampin", 1, "unknown key; keys at admittance: mass, damping"),
])
def test_bad_changes_name_the_key(key: str, value: object, message: str) -> None:
    with pytest.raises(MmctlError, match=message.replace("[", r"\[").replace("]", r"\]")):
        with_value(default_config(), key, value)


def test_a_number_sets_every_entry_of_a_list() -> None:
    cfg = with_value(default_config(), "admittance.damping", 60)
    assert cfg.admittance.damping == (60.0,) * 6
    assert with_value(cfg, "limits.energy", None).limits.energy is None


def _run(core: ControlCore, cycles: int, force: float) -> list[np.ndarray]:
    """``cycles`` cycles of a steady push along x on a robot that moves as commanded:
    the commands (9,)."""
    out = []
    for _ in range(cycles):
        q = core.state.qdot  # (the plant: ideal; only the commands are judged)
        arm = ArmState(core.arm_q.copy(), q[:6].copy(), 0.0, 2, 0)
        now = time.monotonic()
        core.seq += 1
        r = core.step(arm, Wrench(np.array([force, 0.0, 0.0]), np.zeros(3), now, core.seq),
                      Odometry(0.0, 0.0, 0.0, *q[6:], now), T, active=True, now=now)
        assert r.out is not None and r.out.fault is None, r
        core.arm_q += T * r.out.qdot_arm
        out.append(r.out.qdot.copy())
        core.f_h = r.f_h
    return out


@pytest.mark.parametrize(("key", "value"), [
    ("admittance.damping", 30.0),  # faster: the admittance's F / B, 75 / 30 times
    ("limits.ee_speed", 0.1),  # a cap far below the speed: reached, not jumped to
])
def test_a_change_under_a_push_makes_no_velocity_jump(key: str, value: float) -> None:
    cfg = config_from_dict({"limits": {"body_region": "none"}})
    core = ControlCore(cfg)
    core.arm_q = np.array(cfg.robot.q_des, dtype=float)  # type: ignore[attr-defined]
    core.seq = 0  # type: ignore[attr-defined]
    before = _run(core, 1500, 20.0)  # 3 s at 20 N
    v_d0, f_h0 = core.state.v.copy(), core.f_h.copy()
    steps = np.abs(np.diff(np.array(before[-500:]), axis=0)).max(axis=0)
    new_cfg, controller = core.prepare(key, value)
    core.install(new_cfg, controller, key)
    after = _run(core, 1000, 20.0)
    jumps = np.abs(np.diff(np.array([before[-1], *after]), axis=0))
    acc = np.array([*cfg.limits.joint_acceleration, cfg.limits.base_linear_acceleration,
                    cfg.limits.base_linear_acceleration, cfg.limits.base_angular_acceleration])
    assert (jumps.max(axis=0) <= acc * T * (1 + 1e-9)).all(), (jumps.max(axis=0), acc * T)
    assert (steps <= acc * T * (1 + 1e-9)).all()
    def speed(qdot: np.ndarray) -> float:
        return float(np.linalg.norm((core.chain.model.update(
            np.concatenate((core.arm_q, np.zeros(3)))).J @ qdot)[:3]))

    if key == "admittance.damping":  # the admittance's own speed: F / B before and after
        # (within 5 %: the wrist turns, so f_h turns and v follows it 0.05 s behind)
        ratio = [float(np.linalg.norm(v[:3]) / np.linalg.norm(f[:3]))
                 for v, f in ((v_d0, f_h0), (core.state.v, core.f_h))]
        assert ratio == pytest.approx([1 / 75.0, 1 / 30.0], rel=0.05)
    else:  # the commanded end-effector speed comes down to the new cap
        assert speed(before[-1]) > 0.15 and speed(after[-1]) == pytest.approx(value, rel=1e-3)
    assert core.changed == {key: value if key != "admittance.damping" else [value] * 6}
