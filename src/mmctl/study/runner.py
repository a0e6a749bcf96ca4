"""Run the study: every user with every approach through the daemon's control step().

One execution (user u, approach s), at t = kT (T = ``study.dt``), k = 0, 1, ...:

1. the plant's actual ``q``, ``q̇`` give the handle's world position and velocity
   (Pinocchio FK and Jacobian of :class:`mmctl.model.RobotModel`);
2. the simulated human (:mod:`mmctl.sim.human`) returns a world-frame force and maybe
   a switch request; the request reaches the controller only in the switch approach;
3. the force, rotated into the base frame, is ``f_h = (f, 0, 0, 0)`` (the task keeps
   the orientation) and goes with ``q``, ``q̇`` into ``Controller.step``;
4. the commanded arm velocities and base twist drive the plant for one period.

Sample k contributes E_K(kT) (the controller's *measured* energy: actual velocities),
||f_h(kT)|| and ||v(kT)|| (actual end-effector linear speed); the metrics use
k = 1..N with ``N T = T_f``, the first cycle at which the human has finished the last
insertion.  ``x_f = ||p(T_f) - p_des||`` with ``p`` the handle position relative to
the base (FK of the arm joints) and ``p_des = FK(q_des)``.

Executions are independent and deterministic, so a study's results do not depend on
how many worker processes ran them.
"""

from __future__ import annotations

import math
import multiprocessing as mp
import time
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from mmctl.control.metrics import trial_metrics
from mmctl.model import RobotModel
from mmctl.model.planar import base_to_world, rot_z, world_to_base
from mmctl.sim.human import (
    HandleObservation,
    HumanAction,
    SimulatedHuman,
    Task,
    peg_in_hole_task,
)
from mmctl.sim.plant import Plant, initial_state
from mmctl.study.config import StudyConfig
from mmctl.study.results import Execution, Series
from mmctl.study.users import draw_user

Progress = Callable[[int, str], None]
#: Called every cycle with what the human perceived and did (tests, debugging).
Observer = Callable[[HandleObservation, HumanAction], None]


class StudyResult(NamedTuple):
    """Executions ordered by user then strategy; total worker CPU time [s] and cycles."""

    executions: list[Execution]
    cpu_time: float
    cycles: int


def start_configuration(cfg: object) -> np.ndarray:
    """q0 (9,): ``robot.q_init`` or q_des with the base at the origin."""
    robot = cfg.robot  # type: ignore[attr-defined]
    if robot.q_init is not None:
        return np.array(robot.q_init, dtype=float)
    return np.concatenate((np.asarray(robot.q_des, dtype=float), np.zeros(3)))


def study_task(model: RobotModel, q0: np.ndarray, holes: tuple[tuple[float, float], ...]) -> Task:
    """The peg-in-hole layout around the handle at ``q0``: holes in the plane through
    the handle orthogonal to the peg (the tool z axis), offsets along the base heading."""
    kin = model.update(q0, inertia=False)
    axis = rot_z(q0[8]) @ kin.R_base[:, 2]
    mount = model.cfg.arm_mount
    return peg_in_hole_task(kin.p, axis, float(q0[8]), holes,
                            arm_mount_xy=(float(mount[0]), float(mount[1])))


def run_execution(
    study: StudyConfig, user: int, strategy: str, observe: Observer | None = None
) -> tuple[Execution, float, int]:
    """One user with one approach; returns the execution, its CPU time [s] and cycles."""
    from mmctl.config.control import Mode
    from mmctl.control.step import Controller, StepInputs

    cpu0 = time.process_time()
    cfg = study.control_config(strategy)
    model = RobotModel(cfg.robot)
    controller = Controller(cfg, model)
    state = controller.initial_state(strategy)
    plant = Plant(study.plant_params(cfg))
    q0 = start_configuration(cfg)
    ps = initial_state(q0)
    human = SimulatedHuman(draw_user(study.seed, user), study_task(model, q0, study.holes))
    p_des = model.update(np.concatenate((np.asarray(cfg.robot.q_des), np.zeros(3))),
                         inertia=False).p_base
    dt = study.dt
    n_max = int(study.t_max / dt) + 1
    energy = np.zeros(n_max)
    energy_base = np.zeros(n_max)
    force = np.zeros(n_max)
    speed = np.zeros(n_max)
    deviation = np.zeros(n_max)
    loco = np.zeros(n_max, dtype=np.int8)
    f_h = np.zeros(6)
    switches = faults = 0
    k_done = n_max - 1
    p_final = p_des
    for k in range(n_max):
        q, qd = ps.q, ps.qd
        kin = model.update(q, inertia=False)
        v_b = kin.J[:3] @ qd
        v_w = base_to_world(v_b, q[8])
        obs = HandleObservation(k * dt, kin.p, v_w, q[6:9])
        act = human.update(obs)
        if observe is not None:
            observe(obs, act)
        if act.switch_request is not None:  # only the switch strategy uses the sub-mode
            state = controller.set_switch(state, act.switch_request)
            switches += 1
        fw = act.force
        f_h[:3] = world_to_base(fw, q[8])
        state, out = controller.step(state, StepInputs(f_h.copy(), q, qd, dt))
        energy[k] = out.energy.total
        energy_base[k] = out.energy.base
        force[k] = math.sqrt(float(fw @ fw))
        speed[k] = math.sqrt(float(v_b @ v_b))
        dp = kin.p_base - p_des
        deviation[k] = math.sqrt(float(dp @ dp))
        loco[k] = 1 if state.mode is Mode.SWITCH and state.target == "locomotion" else 0
        faults += 1 if out.fault is not None else 0
        if act.done:
            k_done = k
            p_final = kin.p_base
            break
        ps = plant.step(ps, out.qdot_arm, out.base_twist, dt)
    completed = human.finish_time is not None
    if not completed:
        p_final = model.update(ps.q, inertia=False).p_base
    n = max(k_done, 1)
    sl = slice(1, n + 1)
    m = trial_metrics(dt, energy[sl], force[sl], speed[sl], p_final, p_des)
    step_ = study.record_every
    series = Series(
        t=(np.arange(0, n + 1, step_) * dt).astype(np.float32),
        speed=speed[: n + 1 : step_].astype(np.float32),
        energy=energy[: n + 1 : step_].astype(np.float32),
        energy_base=energy_base[: n + 1 : step_].astype(np.float32),
        force=force[: n + 1 : step_].astype(np.float32),
        deviation=deviation[: n + 1 : step_].astype(np.float32),
        locomotion=loco[: n + 1 : step_].copy(),
    )
    ex = Execution(user, strategy, m.E_mean, m.F_mean, m.v_mean, m.x_f, m.T_f,
                   float(energy_base[sl].mean()), float(force[sl].max()), switches, completed,
                   faults, series)
    return ex, time.process_time() - cpu0, k_done + 1


def _work(job: tuple[StudyConfig, int, str]) -> tuple[Execution, float, int]:
    return run_execution(*job)


def run_study(study: StudyConfig, jobs: int = 1, progress: Progress | None = None) -> StudyResult:
    """Every user with every approach, in ``jobs`` processes (1 = in this process)."""
    work = [(study, u, s) for u in range(study.users) for s in study.strategies]
    done: list[tuple[Execution, float, int]] = []

    def tick(r: tuple[Execution, float, int]) -> None:
        done.append(r)
        if progress is not None:
            progress(len(done), f"user {r[0].user} {r[0].strategy}")

    if jobs <= 1 or len(work) == 1:
        for job in work:
            tick(_work(job))
    else:
        methods = mp.get_all_start_methods()
        ctx = mp.get_context("fork" if "fork" in methods else "spawn")
        with ctx.Pool(min(jobs, len(work))) as pool:
            for r in pool.imap_unordered(_work, work):
                tick(r)
    order = {s: i for i, s in enumerate(study.strategies)}
    done.sort(key=lambda r: (r[0].user, order[r[0].strategy]))
    return StudyResult([r[0] for r in done], sum(r[1] for r in done), sum(r[2] for r in done))
