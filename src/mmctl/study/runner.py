"""Run the study: every user with every approach through the robot's control cycle.

Each execution (user u, approach s) runs :class:`mmctl.control.update.Update`, the
pure update the daemon's loop runs (safety state machine, base divider, operator's
commands as inbox values, the control chain), on the simulated robot's plant
(:class:`mmctl.sim.plant.Plant`, the fakes' joints and wheels) in simulated time.
First, hands off the handle, the tare the operator runs before enabling
(``sensor.wrench.tare_samples`` cycles).  Then, at t = kT (T = ``study.dt``), k = 0, 1, ...:

1. the plant's actual ``q``, ``q̇`` give the handle's world position and velocity
   (Pinocchio FK and Jacobian of :class:`mmctl.model.RobotModel`);
2. the simulated human (:mod:`mmctl.sim.human`) returns a world-frame force (motor
   noise included, from the user's own noise stream: the same in every approach) and
   maybe a switch request: the handle has a mode button only in the switch approach,
   so only there does the person press it (and pause for the press);
3. the force becomes what the wrist sensor measures (:class:`mmctl.sim.handle.HandleSensor`:
   sensor frame, its moment, the handle's weight, the sensor's bias) and, with the
   arm's joints and the base's odometry, goes into the cycle: the robot's wrench
   pipeline (tare, gravity compensation, limit, dead band, low-pass, axis mask), then
   admittance, IDK, limits;
4. the commanded speedJ and base twist drive the plant for one period.

Sample k contributes E_K(kT) (the controller's *measured* energy: actual velocities),
||f_h(kT)|| (the force the person applies) and ||v(kT)|| (actual end-effector linear speed); the metrics use
k = 1..N with ``N T = T_f``, the first cycle at which the human has finished the last
insertion.  ``x_f = ||p(T_f) - p_des||`` with ``p`` the handle position relative to
the base (FK of the arm joints) and ``p_des = FK(q_des)``.  Then the person holds the
peg in the last hole for the hold time while the robot runs on: ``x_f_hold`` is the
same distance at the end of the hold (the metrics' samples stop at T_f), and
``x_f_after`` the same distance :data:`~mmctl.study.results.X_F_DELAYS` after T_f.

Executions are independent and deterministic, so a study's results do not depend on
how many worker processes ran them.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import NamedTuple, Protocol

import numpy as np

from mmctl.config import Config
from mmctl.config.control import Mode
from mmctl.control.cycle import CycleChain
from mmctl.control.metrics import trial_metrics
from mmctl.control.update import (
    ENABLE_WITHOUT_DEVICES,
    Command,
    Commands,
    Readings,
    Reply,
    SetSwitch,
    Tare,
    Update,
    UpdateState,
)
from mmctl.errors import ConfigError
from mmctl.model import RobotModel
from mmctl.model.planar import base_to_world, rot_z
from mmctl.sim.handle import HandleSensor
from mmctl.sim.human import (
    HandleObservation,
    HumanAction,
    HumanParams,
    Phase,
    Plane,
    SimulatedHuman,
    Task,
    noise_seed,
    peg_in_hole_task,
    wall_task,
)
from mmctl.sim.plant import Plant
from mmctl.study.config import StudyConfig
from mmctl.study.executor import Executor, run_all
from mmctl.study.results import NEAR_WALL, X_F_DELAYS, Execution, Series
from mmctl.study.users import draw_user
from mmctl.types import ArmState, Odometry, Wrench

Progress = Callable[[int, str], None]
#: Called every cycle with what the human perceived and did (tests, debugging).
Observer = Callable[[HandleObservation, HumanAction], None]


class Variant(Protocol):
    """A changed setting of one execution (:mod:`mmctl.study.sweep`,
    :mod:`mmctl.study.sensitivity`): picklable (it travels with the job to the workers);
    the plain study has none."""

    def config(self, cfg: Config) -> Config:
        """The control (and plant) configuration to use instead of ``cfg``."""

    def chain(self, cfg: Config) -> CycleChain:
        """The cycle chain of ``cfg`` (e.g. with another IDK solver installed)."""

    def user(self, seed: int, index: int) -> HumanParams:
        """User ``index`` of the population of ``seed``."""


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


def study_task(model: RobotModel, q0: np.ndarray, study: StudyConfig) -> Task:
    """The peg-in-hole task of ``study`` around the handle at ``q0`` (9,).

    wall: the seed's layout (:meth:`StudyConfig.layout`) on a vertical wall ahead of
    the peg (the tool z axis, which must be horizontal: ConfigError naming the start
    pose otherwise), one hole at the start handle's height; board: holes in the plane
    through the handle orthogonal to the peg, ``study.holes`` offsets along the base
    heading."""
    kin = model.update(q0, inertia=False)
    axis = rot_z(q0[8]) @ kin.R_base[:, 2]
    mount = model.cfg.arm_mount
    mount_xy = (float(mount[0]), float(mount[1]))
    if study.task == "board":
        return peg_in_hole_task(kin.p, axis, float(q0[8]), study.holes, arm_mount_xy=mount_xy)
    fam = study.wall
    try:
        return wall_task(kin.p, axis, study.layout(float(kin.p[2])), fam.standoff, fam.depth,
                         arm_mount_xy=mount_xy)
    except ValueError as exc:
        key = "robot.q_init" if model.cfg.q_init is not None else "robot.q_des"
        raise ConfigError(key, tuple(round(float(v), 4) for v in q0[:6]),
                          f"{exc}; use a pose with the tool z axis horizontal or "
                          "--task board") from None


def task_of(study: StudyConfig) -> Task:
    """The task every execution of ``study`` runs (world frame; the robot at its start
    pose, the first approach's configuration)."""
    cfg = study.control_config(study.strategies[0])
    q0 = start_configuration(cfg)
    return study_task(RobotModel(cfg.robot), q0, study)


def run_execution(
    study: StudyConfig, user: int, strategy: str, observe: Observer | None = None,
    variant: Variant | None = None,
) -> tuple[Execution, float, int]:
    """One user with one approach (with ``variant``'s changes); returns the execution,
    its CPU time [s] and cycles (the tare's included)."""
    cpu0 = time.process_time()
    cfg = study.control_config(strategy)
    if variant is not None:
        cfg = variant.config(cfg)
    chain = CycleChain(cfg) if variant is None else variant.chain(cfg)
    model = chain.model
    q0 = start_configuration(cfg)
    plant = Plant(cfg, q0)
    sensor = HandleSensor(cfg)
    person = draw_user(study.seed, user) if variant is None else variant.user(study.seed, user)
    # the same noise stream for the user in every approach; a mode button only in the
    # switch condition (the paper's other conditions offer no switching)
    task = study_task(model, q0, study)
    human = SimulatedHuman(person, task, noise_seed=noise_seed(
        study.seed, user), button=strategy == "switch")
    p_des = model.update(np.concatenate((np.asarray(cfg.robot.q_des), np.zeros(3))),
                         inertia=False).p_base
    dt = chain.dt
    update = Update(cfg, chain)
    # (the person holds the handle, its enabling switch with it, throughout)
    clock = _Clock(plant, sensor, model, dt, update.held_inputs)
    # hands off the handle: the tare and the enable the operator runs before the first
    # push, as commands into the update's inbox
    state, tare_cycles = _tare_and_enable(update, clock, plant)
    t0 = clock.t
    n_max = int(study.t_max / dt) + 1
    # after T_f the end-of-trial hold: the person keeps the peg in, the robot runs on
    n_all = n_max + math.ceil(person.hold_time / dt) + 2
    energy = np.zeros(n_all)
    energy_base = np.zeros(n_all)
    force = np.zeros(n_all)
    applied = np.zeros(n_all)
    clearance = np.full(n_all, np.inf)
    deck = _Deck(cfg, task.surface)
    speed = np.zeros(n_all)
    deviation = np.zeros(n_all)
    loco = np.zeros(n_all, dtype=np.int8)
    limited = np.zeros(n_all, dtype=bool)
    switches = faults = 0
    k_done = k_last = n_max - 1
    p_final = p_hold = p_des
    finished = False
    twist = _Z3  # what the drives hold between the twists the update sends
    for k in range(n_all):
        if not finished and k >= n_max:  # the time limit, the task unfinished
            break
        ps = plant.state()
        q, qd = ps.q, ps.qd
        kin = model.update(q, inertia=False)
        v_b = kin.J[:3] @ qd
        v_w = base_to_world(v_b, q[8])
        obs = HandleObservation(clock.t - t0, kin.p, v_w, q[6:9])
        act = human.update(obs)
        if observe is not None:
            observe(obs, act)
        inbox: list[Command] = []
        if act.switch_request is not None:  # only the switch strategy has the button
            inbox.append(SetSwitch(act.switch_request))
            switches += 1
        fw = np.asarray(act.force, dtype=float)
        state, cmds, events = update(state, clock.readings(fw, q=q, qd=qd), inbox)
        _raise_refused(events)
        out = cmds.result
        assert out is not None  # every device is read in the study
        # every metric from what the robot measures (the arm's joints, the wheels'
        # odometry): E_K and the speed from the same velocities; F_h after the sensor
        # chain, the hand's applied force beside it
        energy[k] = out.energy.total
        energy_base[k] = out.energy.base
        f_out = out.f_h[:3]
        force[k] = math.sqrt(float(f_out @ f_out))
        applied[k] = math.sqrt(float(fw @ fw))
        v_meas = out.v[:3]
        speed[k] = math.sqrt(float(v_meas @ v_meas))
        clearance[k] = deck.clearance(q)
        dp = kin.p_base - p_des
        deviation[k] = math.sqrt(float(dp @ dp))
        ctl_state = state.chain.controller
        loco[k] = 1 if ctl_state.mode is Mode.SWITCH and ctl_state.target == "locomotion" else 0
        faults += 1 if out.fault is not None else 0
        limited[k] = out.out is not None and out.out.limit != ""
        k_last = k
        if act.done and not finished:  # T_f: the metrics end here
            finished = True
            k_done = k
            p_final = kin.p_base
        if act.phase is Phase.DONE:  # the end of the hold
            break
        qd_arm, twist = _drive(cmds, twist)
        plant.step(qd_arm, twist, dt)
    completed = human.finish_time is not None
    if not completed:
        p_final = model.update(plant.state().q, inertia=False).p_base
    p_hold = kin.p_base if completed else p_final
    dh = p_hold - p_des
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
    near = clearance[sl] < NEAR_WALL
    # x_f read again during the hold, at fixed delays after T_f (the hold's last cycle
    # at most)
    x_f_after = (tuple(float(deviation[min(k_done + round(d / dt), k_last)])
                       for d in X_F_DELAYS) if completed else (m.x_f,) * len(X_F_DELAYS))
    ex = Execution(user, strategy, m.E_mean, m.F_mean, m.v_mean, m.x_f, m.T_f,
                   float(energy_base[sl].mean()), float(force[sl].max()), switches, completed,
                   faults, series, float(limited[sl].mean()),
                   x_f_hold=math.sqrt(float(dh @ dh)),
                   stopped=latched.value if (latched := state.safety.latched) else "",
                   F_applied=float(applied[sl].mean()),
                   wall_clearance=(float(clearance[sl].min()) if deck.surface is not None
                                   else math.nan),
                   E_base_near=(float(energy_base[sl][near].mean()) if near.any()
                                else math.nan),
                   x_f_after=x_f_after)
    return ex, time.process_time() - cpu0, tare_cycles + k_last + 1


class _Deck:
    """The base's deck as its footprint (a rectangle in base_link, ``robot.deck_size``
    x/y about ``robot.deck_center``) and its distance to the task's surface plane
    (normal toward the robot; None: no surface, distance +inf)."""

    def __init__(self, cfg: Config, surface: Plane | None) -> None:
        sx, sy = cfg.robot.deck_size[0] / 2.0, cfg.robot.deck_size[1] / 2.0
        cx, cy = cfg.robot.deck_center[0], cfg.robot.deck_center[1]
        self.corners = np.array([[cx + a * sx, cy + b * sy] for a in (-1, 1) for b in (-1, 1)])
        self.surface = surface
        if surface is not None:
            self.normal = np.asarray(surface.normal, dtype=float)[:2]
            self.offset = float(np.asarray(surface.point, dtype=float)[:2] @ self.normal)

    def clearance(self, q: np.ndarray) -> float:
        """The smallest distance [m] of the footprint at the base pose q[6:9] (true
        pose: the world's) in front of the plane (negative: through it)."""
        if self.surface is None:
            return math.inf
        c, s = math.cos(q[8]), math.sin(q[8])
        n = self.normal
        # n . (p + R corner) for each corner, R^T n taken once
        nb = np.array([c * n[0] + s * n[1], -s * n[0] + c * n[1]])
        return float(q[6] * n[0] + q[7] * n[1] + (self.corners @ nb).min() - self.offset)


_Z3 = np.zeros(3)
_Z6 = np.zeros(6)
_NO_FORCE = np.zeros(3)


def _tare_and_enable(update: Update, clock: _Clock, plant: Plant) -> tuple[UpdateState, int]:
    """Hands off the handle: the operator's tare, then the enable (the study's base
    has no drives to enable: its enable succeeds), both through the update's inbox.
    Returns the armed state and the cycles it took."""
    dt = update.chain.dt
    state = update.initial_state()
    inbox: list[Command] = [Tare()]
    cycles = 0
    while True:
        state, _cmds, events = update(state, clock.readings(_NO_FORCE), inbox)
        _raise_refused(events)
        plant.step(_Z6, _Z3, dt)
        cycles += 1
        if state.safety.armed:
            return state, cycles
        inbox = []
        if state.chain.wrench.tare_left == 0:
            inbox = list(ENABLE_WITHOUT_DEVICES)


def _raise_refused(events: tuple[object, ...]) -> None:
    """An operator's command the update refused (never in a study that is set up right:
    a configuration error)."""
    for e in events:
        if isinstance(e, Reply) and e.error is not None:
            raise ConfigError("study", "(the control configuration)",
                              f"the update refused the operator's command: {e.error}")


def _drive(cmds: Commands, twist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """What the plant's joints and wheels follow this period: the speedJ (none: at rest,
    as speedStop brings it), and the base twist sent (none: the drives hold the last
    target, as they do between the divided sends; the stop: zero)."""
    if cmds.stop:
        return _Z6, _Z3
    qd_arm = _Z6 if cmds.qd_arm is None else cmds.qd_arm
    if cmds.twist is not None:
        twist = np.asarray(cmds.twist, dtype=float)
    return qd_arm, twist


class _Clock:
    """The study's simulated time and the devices' readings at it: the arm's joints as
    the arm reports them (with its digital inputs: the enabling switch held), the base
    as its wheel encoders report it (the plant's odometry: no slip), and the sensor's
    reading of the person's force (bias and handle weight included) in the sensor's
    actual orientation, one fresh sample per cycle."""

    def __init__(self, plant: Plant, sensor: HandleSensor, model: RobotModel, dt: float,
                 inputs: int = 0):
        self.plant, self.sensor, self.model, self.dt = plant, sensor, model, dt
        self.inputs = inputs
        self.t = 0.0
        self.sequence = 0

    def readings(self, force_world: np.ndarray, q: np.ndarray | None = None,
                 qd: np.ndarray | None = None) -> Readings:
        """The readings of the cycle that starts now, then the clock moves one period.

        ``q``, ``qd``: the plant's actual state now (default: :meth:`Plant.state`); its
        arm part is what the arm reports, its base yaw turns the person's world force
        into the sensor's frame.  The base's pose and twist come from
        :meth:`Plant.odometry`, as the daemon's come from the wheel encoders."""
        if q is None or qd is None:
            q, qd = self.plant.state()
        odo = self.plant.odometry()
        index = self.sequence
        self.t += self.dt
        self.sequence += 1
        r_sensor = self.model.fk_base(q, "sensor").rotation
        w = self.sensor.measure(force_world, float(q[8]), r_sensor)
        t = self.t
        (x, y, yaw), (vx, vy, wz) = odo.pose, odo.twist
        return Readings(index, t, self.dt, ArmState(q[:6], qd[:6], t, 2, 1),
                        Wrench(w[:3], w[3:], t, self.sequence),
                        Odometry(x, y, yaw, vx, vy, wz, t), self.inputs)


def _work(job: tuple[StudyConfig, int, str]) -> tuple[Execution, float, int]:
    return run_execution(*job)


def run_study(study: StudyConfig, jobs: int = 1, progress: Progress | None = None,
              executor: Executor | None = None) -> StudyResult:
    """Every user with every approach, on ``executor`` (default: ``jobs`` local
    processes, 1 = in this process; :mod:`mmctl.study.executor`)."""
    work = [(study, u, s) for u in range(study.users) for s in study.strategies]
    done = run_all(_work, work, executor, jobs, progress,
                   lambda r: f"user {r[0].user} {r[0].strategy}")
    order = {s: i for i, s in enumerate(study.strategies)}
    done.sort(key=lambda r: (r[0].user, order[r[0].strategy]))
    return StudyResult([r[0] for r in done], sum(r[1] for r in done), sum(r[2] for r in done))
