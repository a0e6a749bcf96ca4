"""Tool-load calibration (`mmctl calibrate tool`): the least-squares fit, the poses, the
routine on an ideal arm, the sensor frame's configurable rotation, the config writer,
and the whole command through the real daemon on the simulated robot (its own process),
whose handle differs from the daemon's configuration."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from loopback import free_loopback_host
from mmctl.cli import main
from mmctl.commands.calibrate_tool import report, snippet
from mmctl.commands.yaml_edit import set_entries
from mmctl.config import config_from_dict, default_config, load_config
from mmctl.control.calibration import (
    CHECK_ANGLE,
    CHECK_SKEW,
    CONDITION_WARN,
    SETTLE_TIMEOUT,
    UNCHECKED_HOLD,
    Move,
    ToolCalibration,
    design,
    fit_tool_load,
    gravity_direction,
    plan_poses,
)
from mmctl.control.cycle import CycleChain, Readings
from mmctl.control.wrench import G0
from mmctl.errors import MmctlError
from mmctl.model.robot import RobotModel, sensor_rotation, tool_in_sensor
from mmctl.runtime.ipc import request
from mmctl.sim.handle import HandleSensor
from mmctl.types import ArmState, Odometry, Wrench
from simconfig import LOAD_PROOF, write_sim_config
from waiting import wait_while_alive, with_ur_program

ROOT = Path(__file__).resolve().parents[1]
MASS, COM = 1.1, np.array([0.01, -0.015, 0.1])
BIAS = np.array([3.0, -2.0, 4.0, 0.15, -0.1, 0.05])
NOISE = np.array([0.05] * 3 + [0.002] * 3)  # an Axia80's noise, roughly [N, N m]


def reading(r: np.ndarray, mass: float = MASS, com: np.ndarray = COM,
            bias: np.ndarray = BIAS) -> np.ndarray:
    """The raw wrench at rest, written independently of the module under test."""
    f = r.T @ np.array([0.0, 0.0, -mass * G0])
    return bias + np.concatenate((f, np.cross(com, f)))


# -- the fit -------------------------------------------------------------------------------

def test_the_fit_recovers_mass_com_and_bias_from_noisy_readings() -> None:
    rng = np.random.default_rng(3)
    rots = list(Rotation.random(12, random_state=11).as_matrix())
    wrenches = [reading(r) + rng.normal(0.0, NOISE) for r in rots]
    fit = fit_tool_load(rots, wrenches)
    assert fit.ok and not fit.warnings and fit.poses == 12
    assert fit.mass == pytest.approx(MASS, rel=0.01)
    assert np.abs(fit.com - COM).max() < 0.002
    np.testing.assert_allclose(fit.bias, BIAS, atol=0.05)
    # the residuals are the noise's size, the standard errors cover the error
    assert 0.02 < fit.residual_force_rms < 0.2 and fit.residual_torque_rms < 0.01
    assert abs(fit.mass - MASS) < 4 * fit.mass_std
    assert fit.condition < CONDITION_WARN
    exact = fit_tool_load(rots, [reading(r) for r in rots])
    assert exact.mass == pytest.approx(MASS, abs=1e-12) and exact.residual_force_max < 1e-9
    np.testing.assert_allclose(exact.com, COM, atol=1e-12)


def test_the_design_is_the_wrench_processors_gravity_model() -> None:
    r = Rotation.from_euler("xyz", [20, -35, 70], degrees=True).as_matrix()
    phi = np.concatenate((BIAS[:3], [MASS * G0], BIAS[3:], G0 * MASS * COM))
    np.testing.assert_allclose(design(r) @ phi, reading(r), atol=1e-12)
    np.testing.assert_allclose(gravity_direction(r), r.T @ [0, 0, -1], atol=1e-15)


def test_a_degenerate_pose_set_is_reported() -> None:
    # the wrist spinning under a vertical sensor: gravity always along its z axis
    spins = [Rotation.from_euler("z", a, degrees=True).as_matrix() for a in range(0, 360, 45)]
    fit = fit_tool_load(spins, [reading(r) for r in spins])
    assert not fit.ok and fit.condition == float("inf")
    assert {"mass", "bias_fz", "com_z"} <= set(fit.undetermined)
    assert "degenerate poses" in fit.warnings[0] and "mass" in fit.warnings[0]
    one = fit_tool_load(spins[:1], [reading(spins[0])])
    assert not one.ok and "mass" in one.undetermined
    # tilts of a few degrees only: determined, but poorly
    small = [Rotation.from_rotvec(v).as_matrix() for v in
             ([0, 0, 0], [0.03, 0, 0], [0, 0.03, 0], [-0.03, 0, 0], [0, -0.03, 0])]
    poor = fit_tool_load(small, [reading(r) for r in small])
    assert not poor.undetermined and poor.condition > CONDITION_WARN and not poor.ok
    assert "poorly spread" in poor.warnings[0]
    assert poor.as_dict()["ok"] is False and json.dumps(fit.as_dict())  # plain JSON
    with pytest.raises(ValueError, match="as many orientations"):
        fit_tool_load(spins, [reading(spins[0])])


# -- the poses and the motion ---------------------------------------------------------------

def test_the_poses_turn_only_the_wrist_within_range_and_spread_gravity() -> None:
    cfg = default_config()
    cal = cfg.sensor.calibration
    model = RobotModel(cfg.robot)
    q0 = np.asarray(cfg.robot.q_des)
    plan = plan_poses(model, q0, 8, cal, cfg.limits, cfg.safety.max_condition, 0.25)
    poses = np.array(plan.poses)
    assert len(poses) == 8 and np.array_equal(poses[0], q0)
    assert np.abs(poses[:, :3] - q0[:3]).max() == 0.0  # shoulder and elbow stay
    assert (np.abs(poses[:, 3:] - q0[3:]) <= np.array(cal.wrist_range) + 1e-9).all()
    lo = np.array(cfg.limits.joint_position_min) + cfg.limits.position_margin
    hi = np.array(cfg.limits.joint_position_max) - cfg.limits.position_margin
    assert (poses >= lo).all() and (poses <= hi).all()
    dirs = [gravity_direction(model.fk_base(np.r_[p, 0, 0, 0], "sensor").rotation)
            for p in poses]
    tilt = [np.degrees(np.arccos(np.clip(d @ dirs[0], -1, 1))) for d in dirs]
    assert 0 < tilt[1] <= np.degrees(cal.probe) + 1e-6 and 0 < tilt[2] <= np.degrees(cal.probe) + 1e-6
    assert max(tilt) > 60.0  # then far
    rots = [model.fk_base(np.r_[p, 0, 0, 0], "sensor").rotation for p in poses]
    assert fit_tool_load(rots, [reading(r) for r in rots]).condition < 5.0
    assert all(0 < s <= cal.speed for s in plan.speeds) and len(plan.speeds) == 8
    # a low end-effector cap slows the legs that move the handle down (wrist 3 turns it
    # about its own axis)
    slow = plan_poses(model, q0, 8, cal, cfg.limits, cfg.safety.max_condition, 0.02)
    assert min(slow.speeds) < 0.2 * cal.speed and plan.duration(0.5, 0.5) < slow.duration(0.5, 0.5)
    for mv, speed in zip(slow.moves(), slow.speeds):
        for t in np.linspace(0.0, mv.duration, 20):
            q, qd = mv.at(t)
            v = model.jacobian(np.r_[q, 0, 0, 0])[:3, :6] @ qd
            assert np.linalg.norm(v) <= 0.02 * 1.01 and np.abs(qd).max() <= speed + 1e-12


def test_the_poses_keep_the_handle_in_the_end_effector_box() -> None:
    cfg = default_config()
    model = RobotModel(cfg.robot)
    q0 = np.asarray(cfg.robot.q_des)
    p0 = model.fk_base(np.r_[q0, 0, 0, 0], "tool").translation
    box = np.array([p0 - [0.15, 0.15, 0.1], p0 + [0.15, 0.15, 0.1]])
    plan = plan_poses(model, q0, 8, cfg.sensor.calibration, cfg.limits,
                      cfg.safety.max_condition, 0.5, box.tolist())
    assert len(plan.poses) == 8
    for mv in plan.moves():
        for t in np.linspace(0.0, mv.duration, 30):
            p = model.fk_base(np.r_[mv.at(t)[0], 0, 0, 0], "tool").translation
            assert (p >= box[0] - 1e-3).all() and (p <= box[1] + 1e-3).all()
    free = plan_poses(model, q0, 8, cfg.sensor.calibration, cfg.limits,
                      cfg.safety.max_condition, 0.5)
    reach = max(np.abs(model.fk_base(np.r_[q, 0, 0, 0], "tool").translation - p0).max()
                for q in free.poses)
    assert reach > 0.15  # without the box the handle sweeps beyond it


def test_the_poses_keep_the_robots_parts_apart_by_the_collision_margin() -> None:
    """The routine's own motion is not braked by the self-collision check: its plan
    keeps the margin on every leg (without it, a wrist tilt brings the handle within
    3 cm of the forearm: the self_collision fault a loaded run met)."""
    from mmctl.model.geometry import BodyModel

    cfg = default_config()
    model = RobotModel(cfg.robot)
    body = BodyModel(cfg.robot, model.arm, model.mount)
    q0 = np.asarray(cfg.robot.q_des)
    margin = cfg.safety.collision_margin

    def lowest(plan: Any) -> float:
        return min(body.clearance(mv.at(t)[0]) for mv in plan.moves()
                   for t in np.linspace(0.0, mv.duration, 30))

    free = plan_poses(model, q0, 8, cfg.sensor.calibration, cfg.limits,
                      cfg.safety.max_condition, 0.5)
    assert lowest(free) < margin  # the wrist's range reaches into the margin
    plan = plan_poses(model, q0, 8, cfg.sensor.calibration, cfg.limits,
                      cfg.safety.max_condition, 0.5, None, body.clearance, margin)
    assert len(plan.poses) >= 6 and lowest(plan) >= margin - 1e-3


def test_a_move_is_a_synchronised_trapezoid_within_speed_and_acceleration() -> None:
    a, b = np.zeros(6), np.array([0, 0, 0, 0.4, -1.2, 2.0])
    mv = Move(a, b, 0.3, 0.5)
    assert mv.duration == pytest.approx(2.0 / 0.3 + 0.3 / 0.5)
    ts = np.arange(0.0, mv.duration + 0.01, 0.002)
    q = np.array([mv.at(t)[0] for t in ts])
    qd = np.array([mv.at(t)[1] for t in ts])
    assert np.abs(qd).max() <= 0.3 + 1e-12
    assert np.abs(np.diff(qd, axis=0)).max() / 0.002 <= 0.5 + 1e-9
    np.testing.assert_allclose(q[-1], b, atol=1e-12)
    np.testing.assert_allclose(np.diff(q, axis=0) / 0.002, 0.5 * (qd[1:] + qd[:-1]), atol=1e-3)
    short = Move(a, np.array([0, 0, 0, 0, 0.01, 0]), 0.3, 0.5)  # never reaches the speed
    assert short.duration == pytest.approx(2 * np.sqrt(0.01 / 0.5))


def _ideal_run(cfg: Any, push: np.ndarray | None = None, push_at: float = 1e9,
               base_drift: float = 0.0, scaling: float = 1.0, pose_gaps: int = 0,
               tell_repeats: bool = True, late_sensor: bool = False,
               late_pose: float = 0.0, clock_jump: tuple[float, float] = (1e9, 0.0),
               starved_from: float = 1e9, commands: list[tuple[float, np.ndarray]] | None = None
               ) -> tuple[ToolCalibration, float]:
    """The routine on an arm that follows speedJ (times ``scaling``, the UR's speed
    slider) on a 4 rad/s^2 ramp, and the simulated sensor (sim.handle_*), 500 Hz.
    ``pose_gaps``: every second the arm's pose is repeated for that many cycles while
    the arm moves on at its last speed (no command reaches it either) and the sensor
    streams: a loaded machine's RTDE; ``tell_repeats`` False: the routine is not told
    that the pose is a repeat (nor a sample's age); ``late_sensor``: in those gaps the
    pose is new and the sensor's samples are late instead (each one the gap's first
    measurement: a starved link); ``late_pose`` [s]: in those gaps every pose is new but
    that much old (a starved arm link draining its backlog), with its controller time
    told (unless ``tell_repeats`` is False); ``clock_jump`` (at [s], by [s]): from then
    on the controller's clock is that much behind ours (a simulated controller that
    dropped steps under load); ``starved_from`` [s]: from then on every wrench is the one
    measured then, its age told (a sensor link that no longer gets the CPU), the poses
    new; ``commands``: (time, command) of each cycle are appended to it."""
    model = RobotModel(cfg.robot)
    sensor = HandleSensor(cfg)
    q = np.r_[np.asarray(cfg.robot.q_des), 0.0, 0.0, 0.0]
    qd = np.zeros(9)
    plan = plan_poses(model, q[:6], 6, cfg.sensor.calibration, cfg.limits,
                      cfg.safety.max_condition, 0.5)
    w = cfg.sensor.wrench
    cal = ToolCalibration(plan, cfg.sensor.calibration, (w.handle_mass, w.handle_com), model,
                          q[6:], 0.0)
    t, seq, dt = 0.0, 0, 0.002
    seen, seen_qd, repeats = q.copy(), qd.copy(), 0
    late: tuple[np.ndarray, float] | None = None
    history: list[tuple[float, np.ndarray, np.ndarray]] = []
    pose_time = 0.0
    while cal.running and t < 120.0:
        t += dt
        seq += 1
        force = push if push is not None and t >= push_at else np.zeros(3)
        raw = sensor.measure(force, 0.0, model.fk_base(q, "sensor").rotation)
        gap = round(t / dt) % 500 < pose_gaps
        age = 0.0
        if t >= starved_from or (gap and late_sensor):
            if late is None:
                late = (raw, t)
            raw, age = late[0], t - late[1]
        else:
            late = None
        history.append((t, q.copy(), qd.copy()))
        del history[:-1000]
        if gap and late_pose > 0.0:
            pose_time, seen, seen_qd = min(history, key=lambda h: abs(h[0] - (t - late_pose)))
            repeats = 0
        elif gap and not late_sensor:
            repeats += 1
        else:
            seen, seen_qd, repeats, pose_time = q.copy(), qd.copy(), 0, t
        cmd = cal.step(seen, seen_qd, raw, seq, t, scaling=scaling,
                       hold=repeats >= cfg.arm.hold_cycles,
                       pose_new=repeats == 0 or not tell_repeats,
                       sample_age=age if tell_repeats else 0.0,
                       pose_time=pose_time + 100.0 - (clock_jump[1] if t >= clock_jump[0]
                                                      else 0.0) if tell_repeats else None)
        assert np.abs(cmd).max() <= max(plan.speeds) + 1e-12
        if commands is not None:
            commands.append((t, cmd.copy()))
        if not gap:
            qd[:6] += np.clip(scaling * cmd - qd[:6], -4.0 * dt, 4.0 * dt)
        q[:6] += qd[:6] * dt
        q[6] += base_drift * dt
    return cal, t


SIM_HANDLE = {"sim": {"handle_mass": MASS, "handle_com": COM.tolist(),
                      "sensor_bias": BIAS.tolist()},
              "robot": {"sensor_rotation": [0.0, 0.0, 0.5236]},
              "sensor": {"calibration": {"speed": 1.0, "acceleration": 2.0,
                                         "settle_time": 0.2, "average_time": 0.3}}}


def test_the_routine_weighs_every_pose_and_returns_to_the_start() -> None:
    cfg = config_from_dict(SIM_HANDLE)
    cal, t = _ideal_run(cfg)
    assert cal.phase == "done" and cal.error is None and len(cal.samples) == 6
    fit = fit_tool_load([s.rotation for s in cal.samples], [s.wrench for s in cal.samples])
    assert fit.mass == pytest.approx(MASS, rel=1e-6)
    np.testing.assert_allclose(fit.com, COM, atol=1e-6)
    np.testing.assert_allclose(fit.bias, BIAS, atol=1e-6)
    # the push check never came near its thresholds on a handle that is not as configured
    assert cal.peak_force < 0.5 * cfg.sensor.calibration.abort_force
    assert cal.peak_torque < 0.5 * cfg.sensor.calibration.abort_torque
    assert cal.progress()["weighed"] == 6 and t < 30.0
    # the progress says finishing until the daemon has acted on the end
    assert cal.progress()["phase"] == "finishing"
    cal.closed = True
    assert cal.progress()["phase"] == "done"
    # the pendant's speed slider at 30 %: slower, the same poses, no timeout
    slow, t_slow = _ideal_run(cfg, scaling=0.3)
    assert slow.phase == "done" and t_slow > 2.0 * t
    assert len(slow.samples) == 6 and fit_tool_load(
        [s.rotation for s in slow.samples],
        [s.wrench for s in slow.samples]).mass == pytest.approx(MASS, rel=1e-6)


def test_a_repeated_arm_pose_or_a_late_sample_is_no_push() -> None:
    """A loaded machine's RTDE repeats the arm's pose for tens of ms while the wrist
    turns at 1 rad/s and the sensor streams (seen in CI: 22 repeats over ~0.5 s of a
    starved loop): compared with the repeated pose, the handle's weight looks turned,
    a 5.2 N "push" that aborted the routine; the check waits for the next new pose."""
    cfg = config_from_dict(SIM_HANDLE)
    cal, _ = _ideal_run(cfg, pose_gaps=250)
    assert cal.phase == "done" and cal.error is None and len(cal.samples) == 6
    assert cal.peak_force < 0.5 * cfg.sensor.calibration.abort_force, cal.peak_force
    # what the check saw before: the same run, the repeats not told
    cal, _ = _ideal_run(cfg, pose_gaps=250, tell_repeats=False)
    assert cal.phase == "aborted" and "on the handle beyond its weight" in (cal.error or "")
    # the same with the sensor's samples late instead of the arm's poses
    cal, _ = _ideal_run(cfg, pose_gaps=250, late_sensor=True)
    assert cal.phase == "done" and cal.error is None and len(cal.samples) == 6
    assert cal.peak_force < 0.5 * cfg.sensor.calibration.abort_force, cal.peak_force
    cal, _ = _ideal_run(cfg, pose_gaps=250, late_sensor=True, tell_repeats=False)
    assert cal.phase == "aborted" and "on the handle beyond its weight" in (cal.error or "")
    # poses new to the loop but 0.5 s late (a starved arm link draining a backlog):
    # judged by their controller time against the best lag seen
    cal, _ = _ideal_run(cfg, pose_gaps=250, late_pose=0.5)
    assert cal.phase == "done" and cal.error is None and len(cal.samples) == 6
    assert cal.peak_force < 0.5 * cfg.sensor.calibration.abort_force, cal.peak_force
    cal, _ = _ideal_run(cfg, pose_gaps=250, late_pose=0.5, tell_repeats=False)
    assert cal.phase == "aborted" and "on the handle beyond its weight" in (cal.error or "")
    # a push during the gaps is still caught, at the next new pose
    cal, t = _ideal_run(cfg, push=np.array([0.0, 8.0, 0.0]), push_at=4.1, pose_gaps=250)
    assert cal.phase == "aborted" and t == pytest.approx(4.5, abs=0.01), t
    assert "on the handle beyond its weight" in (cal.error or "")


def test_a_routine_that_cannot_check_for_a_hand_holds_the_arm_then_aborts() -> None:
    """A machine so busy that no wrench comes within the check's skew of a pose (CI under
    load: a whole 3-s push during the moves went unchecked and the routine finished):
    the arm is held within UNCHECKED_HOLD, and the routine aborts after SETTLE_TIMEOUT."""
    cfg = config_from_dict(SIM_HANDLE)
    cmds: list[tuple[float, np.ndarray]] = []
    cal, _ = _ideal_run(cfg, commands=cmds)  # the same routine, checked throughout
    moving = [t for t, c in cmds if np.abs(c).max() > 0.1]
    starved = moving[len(moving) // 2]  # in the middle of a move
    cmds.clear()
    cal, t = _ideal_run(cfg, starved_from=starved, commands=cmds)
    assert cal.phase == "aborted" and "too busy to calibrate safely" in (cal.error or ""), cal.error
    # the last checked pair: at most CHECK_SKEW after the starvation began (the skew
    # grows one period per cycle), so the abort comes SETTLE_TIMEOUT after it
    assert starved < t - SETTLE_TIMEOUT <= starved + CHECK_SKEW, (starved, t)
    held = [np.abs(c).max() for s, c in cmds if s > starved + CHECK_SKEW + UNCHECKED_HOLD]
    assert held and max(held) == 0.0, max(held)
    assert max(np.abs(c).max() for s, c in cmds if s < starved) > 0.1  # it was moving
    # moving, the hold comes sooner: once the skew turned the wrist by CHECK_ANGLE
    speed = max(np.abs(c).max() for s, c in cmds if starved - 0.01 < s < starved)
    soon = starved + CHECK_ANGLE / speed + UNCHECKED_HOLD + 0.005
    assert max(np.abs(c).max() for s, c in cmds if soon < s) == 0.0


def test_a_push_or_a_moving_base_aborts_the_routine() -> None:
    cfg = config_from_dict(SIM_HANDLE)
    cal, t = _ideal_run(cfg, push=np.array([0.0, 8.0, 0.0]), push_at=4.0)
    assert cal.phase == "aborted" and t == pytest.approx(4.0, abs=0.01)
    assert "on the handle beyond its weight" in (cal.error or "")
    # also after the controller's clock fell 0.3 s behind ours (a simulated controller
    # that dropped steps): the lag's floor follows within LAG_WINDOW, the check goes on
    cal, t = _ideal_run(cfg, push=np.array([0.0, 8.0, 0.0]), push_at=6.0,
                        clock_jump=(1.5, 0.3))
    assert cal.phase == "aborted" and t == pytest.approx(6.0, abs=0.01)
    assert "on the handle beyond its weight" in (cal.error or "")
    assert not cal.step(np.zeros(9), np.zeros(9), np.zeros(6), 0, 5.0).any()  # stays at zero
    cal, _ = _ideal_run(cfg, base_drift=0.01)
    assert cal.phase == "aborted" and "the base moved" in (cal.error or "")


# -- the sensor frame's rotation -------------------------------------------------------------

def test_the_sensor_frame_turns_by_robot_sensor_rotation() -> None:
    rpy = (0.1, -0.2, 0.5236)
    cfg = config_from_dict({"robot": {"sensor_rotation": list(rpy)}})
    model = RobotModel(cfg.robot)
    q = np.r_[np.asarray(cfg.robot.q_des), 0, 0, 0] + 0.1
    r_fs = Rotation.from_euler("xyz", rpy).as_matrix()  # extrinsic x, y, z = Rz Ry Rx
    np.testing.assert_allclose(sensor_rotation(cfg.robot), r_fs, atol=1e-12)
    flange = model.fk_base(q, "flange")
    sensor = model.fk_base(q, "sensor")
    np.testing.assert_allclose(sensor.rotation, flange.rotation @ r_fs, atol=1e-12)
    np.testing.assert_allclose(sensor.translation, flange.act(np.array(cfg.robot.sensor_offset)),
                               atol=1e-12)
    np.testing.assert_allclose(model.fk_base(q, "tool").rotation, flange.rotation, atol=1e-12)
    lever = np.subtract(cfg.robot.tool_offset, cfg.robot.sensor_offset)
    np.testing.assert_allclose(tool_in_sensor(cfg.robot), r_fs.T @ lever, atol=1e-12)
    assert np.allclose(sensor_rotation(default_config().robot), np.eye(3))


def test_a_turned_sensor_still_gives_the_persons_push_in_the_control_frame() -> None:
    """The simulated sensor (turned 30 deg, a handle as configured) and the daemon's
    chain agree: after a tare the processed wrench is the push, at any orientation."""
    cfg = config_from_dict({"robot": {"sensor_rotation": [0.2, 0.0, 0.5236]},
                            "sensor": {"wrench": {"deadband_force": 0.0, "deadband_torque": 0.0,
                                                  "lowpass_cutoff": 500.0, "tare_samples": 2,
                                                  "axis_mask": [True] * 6}}})
    chain = CycleChain(cfg)
    sensor = HandleSensor(cfg)
    state = chain.initial_state()
    state = state._replace(wrench=chain.wrench.start_tare(state.wrench))
    push = np.array([4.0, -3.0, 2.0])
    odom = Odometry(0, 0, 0, 0, 0, 0, 0.0)
    for k in range(400):
        q = np.asarray(cfg.robot.q_des) + (0.0 if k < 2 else 0.3 * np.sin(k / 50.0))
        r = chain.model.fk_base(np.r_[q, 0, 0, 0], "sensor").rotation
        w = sensor.measure(push if k >= 2 else np.zeros(3), 0.0, r)
        t = k * 0.002
        state, out = chain.cycle(state, Readings(
            ArmState(q, np.zeros(6), t, 2, 1), Wrench(w[:3], w[3:], t, k), odom, 0.002, False),
            t)
    np.testing.assert_allclose(out.f_h[:3], push, atol=0.05)
    assert np.abs(out.f_h[3:]).max() < 0.01  # it acts at the tool: no torque about it


# -- the config writer -------------------------------------------------------------------------

@pytest.mark.parametrize("text", [
    (ROOT / "config" / "robot.yaml").read_text(),  # sensor: without wrench:
    ("name: x\nsensor:\n  wrench:\n    handle_mass: 0.6  # kg\n    handle_com:\n"
     "      - 0\n      - 0\n      - 0.08\n    tare_samples: 50\narm: {host: a}\n"),
    "name: x\n",
    "",
])
def test_the_fit_goes_into_sensor_wrench_and_nothing_else_changes(tmp_path: Path, text: str) -> None:
    out = set_entries(text, ("sensor", "wrench"),
                      {"handle_mass": "1.10000", "handle_com": "[0.01000, -0.01500, 0.10000]"},
                      "calibrated by mmctl calibrate tool")
    path = tmp_path / "c.yaml"
    path.write_text(out)
    w = load_config(path).sensor.wrench
    assert w.handle_mass == 1.1 and list(w.handle_com) == [0.01, -0.015, 0.1]
    kept = [ln for ln in text.splitlines() if "handle_" not in ln and not ln.startswith("      - ")]
    assert all(ln in out.splitlines() for ln in kept), out
    if "tare_samples" in text:
        assert load_config(path).sensor.wrench.tare_samples == 50


def test_the_report_and_the_yaml_snippet() -> None:
    rots = list(Rotation.random(8, random_state=5).as_matrix())
    fit = fit_tool_load(rots, [reading(r) for r in rots]).as_dict()
    st = {"fit": fit, "configured": {"handle_mass": 0.6, "handle_com": [0.0, 0.0, 0.08]},
          "elapsed_s": 44.5}
    text = report(st)
    assert text.startswith("mass: 1.1000 kg +- 0.0000 (configured 0.6)")
    assert "centre of mass: [0.0100, -0.0150, 0.1000] m" in text and "warning" not in text
    w = yaml.safe_load(snippet(fit))["sensor"]["wrench"]
    assert w == {"handle_mass": 1.1, "handle_com": [0.01, -0.015, 0.1]}
    spins = [Rotation.from_euler("z", a, degrees=True).as_matrix() for a in (0, 90, 180)]
    bad = fit_tool_load(spins, [reading(r) for r in spins]).as_dict()
    assert "warning: degenerate poses" in report({**st, "fit": bad})


def test_an_inline_section_is_not_rewritten() -> None:
    with pytest.raises(MmctlError, match=r"sensor\.wrench is written inline"):
        set_entries("sensor:\n  wrench: {handle_mass: 1}\n", ("sensor", "wrench"),
                    {"handle_mass": "2"})


# -- through the daemon on the simulated robot -------------------------------------------------

@dataclass
class Daemon:
    proc: subprocess.Popen[bytes]
    config: Path
    socket: Path
    out: Path

    def call(self, cmd: str, **args: Any) -> Any:
        return request(self.socket, cmd, timeout=60.0, **args)

    def sim(self, cmd: str, **args: Any) -> Any:
        return request(self.config.parent / "sim.sock", cmd, timeout=60.0, **args)

    def log_text(self) -> str:
        return self.out.read_text(errors="replace")

    def wait_for(self, pred: Any, what: str, timeout: float = 180.0) -> Any:
        return wait_while_alive(pred, what, self.proc, "mmctl run",
                                with_ur_program(self.log_text, self.config.parent / "sim.sock"),
                                timeout)


@pytest.fixture(scope="module")
def daemon(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Daemon]:
    """`mmctl run` (its simulated robot a process of its own) on its own loopback
    address: the person off, armed after its tare, a handle unlike the configured one
    (0.6 kg at [0, 0, 0.08] m) under a sensor turned 30 deg on the flange."""
    tmp = tmp_path_factory.mktemp("calibrate")
    cfg = write_sim_config(free_loopback_host(244), tmp, {
        **LOAD_PROOF, "name": "calibrate-test",
        "sim": {"human": False, "auto_enable": True, **SIM_HANDLE["sim"]},
        "robot": SIM_HANDLE["robot"],
        "daemon": {**LOAD_PROOF["daemon"], "socket_path": str(tmp / "mmctl.sock")},
        "sensor": {**LOAD_PROOF["sensor"], **SIM_HANDLE["sensor"]}})
    out = tmp / "daemon.log"
    with out.open("ab") as f:
        proc = subprocess.Popen([sys.executable, "-m", "mmctl.cli", "run", "--config", str(cfg),
                                 "--log-json"], stdout=f, stderr=subprocess.STDOUT, cwd=str(ROOT),
                                env={**os.environ, "PYTHONUNBUFFERED": "1"})
    d = Daemon(proc, cfg, tmp / "mmctl.sock", out)
    try:
        d.wait_for(lambda: d.call("status")["state"] == "armed", "the daemon armed")
        yield d
    finally:
        if proc.poll() is None:
            proc.send_signal(2)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(30)


def _cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    cap = capsys.readouterr()
    return rc, cap.out, cap.err


@pytest.mark.timeout(600)
def test_calibrate_tool_recovers_the_simulated_handle(daemon: Daemon, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    q_start = daemon.sim("status")["arm_q"]
    base_start = daemon.sim("status")["base_pose"]
    target = tmp_path / "robot.yaml"
    target.write_text((ROOT / "config" / "robot.yaml").read_text())
    t0 = time.monotonic()
    rc, out, err = _cli(capsys, "calibrate", "tool", "--poses", "6", "--json", "--write",
                        str(target), "--config", str(daemon.config))
    seconds = time.monotonic() - t0
    assert rc == 0, err + daemon.log_text()[-3000:]
    st = json.loads(out)
    fit = st["fit"]
    print(f"calibration: {seconds:.1f} s, fit {json.dumps(fit)}, push check's peak "
          f"{json.dumps(st['peak_deviation'])}", file=sys.__stderr__)
    assert st["phase"] == "done" and fit["ok"] and fit["poses"] == 6 and not fit["warnings"]
    assert fit["mass_kg"] == pytest.approx(MASS, rel=0.01)
    assert np.abs(np.array(fit["com_m"]) - COM).max() < 0.002
    assert (np.abs(np.array(fit["bias"]) - BIAS) <= [0.1] * 3 + [0.01] * 3).all(), fit["bias"]
    assert st["configured"] == {"handle_mass": 0.6, "handle_com": [0.0, 0.0, 0.08]}
    w = load_config(target).sensor.wrench
    assert w.handle_mass == round(fit["mass_kg"], 5) and "calibrated by" in target.read_text()
    # back where it started, armed, the base never moved
    sim = daemon.sim("status")
    assert np.abs(np.array(sim["arm_q"]) - q_start).max() < 0.01
    assert np.abs(np.array(sim["base_pose"]) - base_start).max() < 1e-3
    assert daemon.call("status")["state"] == "armed"
    assert daemon.call("status")["calibration"]["phase"] == "done"
    rc, out, _ = _cli(capsys, "status", "--config", str(daemon.config))
    assert rc == 0 and "tool calibration: done at pose 1/6, 6 weighed" in out, out


@pytest.mark.timeout(600)
def test_a_push_during_calibration_stops_the_robot(daemon: Daemon,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    if daemon.call("status")["state"] != "armed":
        daemon.wait_for(lambda: _enabled(daemon), "the daemon armed")
    started = daemon.wait_for(lambda: _started(daemon, 8), "a calibration started")
    assert started["poses"] == 8 and started["estimated_s"] > 5
    daemon.wait_for(lambda: daemon.call("calibrate", action="status")["pose"] >= 4,
                    "the wrist on its way to pose 4")
    assert daemon.call("status")["calibration"]["phase"] in ("moving", "settling", "weighing")
    stops = daemon.call("status")["commands"]["stop"]
    daemon.sim("push", force=[0.0, 12.0, 0.0], seconds=3.0)
    rep = daemon.wait_for(lambda: (r := daemon.call("calibrate", action="status"))["phase"]
                          == "aborted" and r, "the calibration aborted")
    assert "on the handle beyond its weight" in rep["error"], rep
    # the stop went out in the cycle that found the push; the next cycle's update takes
    # the Disable (a starved loop's next cycle can come after this status request)
    st = daemon.wait_for(lambda: (s := daemon.call("status"))["state"] == "disarmed" and s,
                         "the daemon disarmed", timeout=30)
    assert st["commands"]["stop"] > stops, st["commands"]
    # the arm is at rest, and stays there (the push goes on for seconds)
    daemon.wait_for(lambda: np.abs(daemon.sim("status")["arm_qd"]).max() < 1e-3, "the arm at rest",
                    timeout=30)
    q = np.array(daemon.sim("status")["arm_q"])
    time.sleep(0.5)
    assert np.abs(np.array(daemon.sim("status")["arm_q"]) - q).max() < 1e-3
    assert '"calibration_aborted"' in daemon.log_text()
    # disarmed: a new calibration is refused, with the reason
    rc, _, err = _cli(capsys, "calibrate", "tool", "--config", str(daemon.config))
    assert rc == 2 and "refused to calibrate: the robot is disarmed" in err, err


@pytest.mark.timeout(600)
def test_the_operators_abort_stops_it_and_bad_requests_are_refused(
        daemon: Daemon, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = ["--config", str(daemon.config)]
    rc, _, err = _cli(capsys, "calibrate", "tool", "--poses", "3", *cfg)
    assert rc == 2 and "poses = 3: must be a whole number within [4, 50]" in err, err
    # the enabling switch released: the armed robot rests (the wrist is where the push
    # stopped it, where the configured handle's weight is not the true one's), and the
    # calibration needs no hand on the handle's switch
    daemon.sim("push", force=None)
    daemon.sim("enabling", held=False)
    if daemon.call("status")["state"] != "armed":
        daemon.wait_for(lambda: _enabled(daemon), "the daemon armed again")
    daemon.wait_for(lambda: _started(daemon, 4), "a calibration started (the arm still)")
    rc, _, err = _cli(capsys, "calibrate", "tool", *cfg)  # one at a time
    assert rc == 2 and "refused to calibrate: a calibration is running" in err, err
    daemon.wait_for(lambda: daemon.call("calibrate", action="status")["pose"] >= 2,
                    "the wrist on its way to pose 2")
    rep = daemon.call("calibrate", action="abort")  # what Ctrl-C on the command sends
    assert rep["phase"] == "aborted" and rep["error"] == "aborted by the operator", rep
    assert daemon.call("status")["state"] == "disarmed"
    daemon.wait_for(lambda: np.abs(daemon.sim("status")["arm_qd"]).max() < 1e-3,
                    "the arm at rest", timeout=30)
    daemon.sim("enabling", held=True)


def _enabled(d: Daemon) -> bool:
    try:
        d.call("enable")
    except MmctlError:
        return False
    return bool(d.call("status")["state"] == "armed")


def _started(d: Daemon, poses: int) -> dict[str, Any] | None:
    """Start one (its reply); None while refused because the arm still moves (after an
    enable the null space takes it back toward q_des)."""
    try:
        reply: dict[str, Any] = d.call("calibrate", action="start", poses=poses)
    except MmctlError as exc:
        if "the robot is moving" in str(exc):
            return None
        raise
    return reply
