"""Tool-load calibration, pure: where the wrist turns, how it gets there, and the fit.

`mmctl calibrate tool` weighs the handle (docs/hand-guiding.md): with hands off, the
daemon's loop turns the wrist through N orientations, averages the raw wrench at each
and fits the sensor's bias, the handle's mass and its centre of mass.

**Model.**  The raw wrench with nobody at the handle, in the sensor frame, is the bias
plus the handle's weight (what :class:`~mmctl.control.wrench.WrenchProcessor`
compensates)::

    f = b_f + m g_s,   t = b_t + (m c) x g_s = b_t - [g_s]x (m c),   g_s = R^T (0, 0, -g0)

with ``R`` the sensor's axes in the base frame (FK).  It is linear in the ten unknowns
``theta = (b_f (3), m, b_t (3), p = m c (3))``: one pose adds six rows to the design
matrix, which :func:`design` builds with the mass column in newtons (``m g0``) and the
centre-of-mass columns in newton metres (``g0 m c``), so that its condition number
(:attr:`ToolLoadFit.condition`) compares like with like.  Two gravity directions give
the mass and the force bias; the centre of mass (torque differences ``(m c) x (g_i -
g_j)``) needs the differences to span a plane, which three distinct directions always
do (a line meets the sphere twice at most); the torque bias then follows.  Poses that
turn only about the gravity axis (wrist 3 under a vertical tool) are all one direction
and determine neither: the fit names what stays undetermined
(:attr:`ToolLoadFit.undetermined`, :attr:`~ToolLoadFit.warnings`); directions close
together determine it poorly (a large condition number).

**Poses** (:func:`plan_poses`): the start pose, two short *probe* tilts
(``sensor.calibration.probe``), then orientations of wrists 1-3 within
``wrist_range`` of the start chosen one by one to be as far as possible (in gravity
direction seen by the sensor) from those already chosen, ordered as a short tour.
Every pose lies inside the joint limits by ``limits.position_margin`` and every move
stays clear of singular poses.

**Motion** (:class:`Move`): a synchronised trapezoid in joint space (every joint starts
and ends together, the longest at the leg's speed), tracked by a velocity command
``qd = qd_ref + K (q_ref - q)`` clipped to the speed.

**Routine** (:class:`ToolCalibration`): stepped once per control cycle by the daemon's
loop; it records, moves, settles, averages, checks every fresh sample against the
weight predicted from the poses weighed so far (a push is a hand on the handle: it
aborts), and ends back at the start pose.  No I/O, no clock: the caller passes ``now``.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np

from mmctl.config.control import LimitsConfig
from mmctl.config.sensor import ToolCalibrationConfig
from mmctl.control.wrench import G0
from mmctl.model.robot import RobotModel
from mmctl.types import Vec

#: the fit's unknowns, in the order of :func:`design`'s columns
PARAMETERS = ("bias_fx", "bias_fy", "bias_fz", "mass", "bias_tx", "bias_ty", "bias_tz",
              "com_x", "com_y", "com_z")

#: design condition number above which the poses are reported as poorly spread
CONDITION_WARN = 20.0
#: relative singular value below which a direction of the unknowns is undetermined
_RANK_TOL = 1e-6
#: [kg] below this there is no handle whose centre of mass could be found
MIN_MASS = 0.01
#: weight of the prior rows (configured mass and centre of mass) in the push check's
#: running fit, relative to one pose's rows: two poses 6 deg apart outweigh it
PRIOR_WEIGHT = 0.1

#: [1/s] position feedback of the motion
GAIN = 3.0
#: [rad] / [rad/s] a pose is reached when every joint is this close and this slow
POSITION_TOLERANCE = 0.005
VELOCITY_TOLERANCE = 0.005
#: [s] how long a pose may take to settle after its move's planned end
SETTLE_TIMEOUT = 5.0
#: [rad] the most the wrist may have turned between a pose and the wrench the push check
#: compares it with: the pair's skew times the fastest joint's speed (1.1 kg turned by
#: 0.01 rad is 0.1 N, 2 % of the default abort_force)
CHECK_ANGLE = 0.01
#: [s] the oldest pose or wrench the push check uses (the arm at rest; moving,
#: CHECK_ANGLE decides: 10 ms at 1 rad/s)
CHECK_SKEW = 0.25
#: [s] without a checked pair for this long the routine holds the arm (zero command,
#: its motion's clock stands) until one comes: the wrist never moves unchecked for
#: longer (a starved machine, seen in CI, let a whole 3-s push pass unchecked)
UNCHECKED_HOLD = 0.1
#: [s] the pose lag's floor is the smallest over the last one to two of these: longer
#: than a starved arm link's backlog (hundreds of ms), short enough to follow clocks
#: that drift apart (a simulated controller's under load)
LAG_WINDOW = 2.0
#: fresh sensor samples a pose's average needs at least
MIN_SAMPLES = 10
#: [rad] the least angle between two chosen gravity directions
_MIN_SPREAD = math.radians(2.0)
#: [m] / [rad] the base may drift this far during the calibration before it aborts
BASE_TOLERANCE = (0.01, 0.02)

_EZ_DOWN = np.array([0.0, 0.0, -1.0])


def _skew(v: Vec) -> Vec:
    return np.array(((0.0, -v[2], v[1]), (v[2], 0.0, -v[0]), (-v[1], v[0], 0.0)))


def gravity_direction(r_base_sensor: Vec) -> Vec:
    """(3,) the unit direction of gravity in the sensor frame, ``R^T (0, 0, -1)``."""
    d: Vec = -np.asarray(r_base_sensor, dtype=float)[2]
    return d


def design(r_base_sensor: Vec) -> Vec:
    """(6, 10) rows of one pose: ``wrench = design(R) @ phi`` for the scaled unknowns
    ``phi = (b_f, m g0, b_t, g0 m c)`` [N, N, N m, N m]."""
    u = gravity_direction(r_base_sensor)
    a = np.zeros((6, 10))
    a[:3, :3] = np.eye(3)
    a[:3, 3] = u
    a[3:, 4:7] = np.eye(3)
    a[3:, 7:] = -_skew(u)
    return a


def _stack(rotations: Sequence[Vec]) -> Vec:
    return np.vstack([design(r) for r in rotations])


def solve(rotations: Sequence[Vec], wrenches: Sequence[Vec],
          prior: tuple[float, Vec] | None = None) -> Vec:
    """(10,) the scaled unknowns ``phi`` by least squares; with ``prior`` = (mass [kg],
    centre of mass (3,) [m]) rows pulling mass and centre of mass toward it with
    :data:`PRIOR_WEIGHT` (what the push check predicts with while few poses are in)."""
    a = _stack(rotations)
    y = np.concatenate([np.asarray(w, dtype=float) for w in wrenches])
    if prior is not None:
        m0, c0 = prior
        rows = np.zeros((4, 10))
        rows[0, 3] = PRIOR_WEIGHT
        rows[1:, 7:] = PRIOR_WEIGHT * np.eye(3)
        a = np.vstack((a, rows))
        y = np.concatenate((y, PRIOR_WEIGHT * G0 * np.concatenate(([m0], m0 * np.asarray(c0)))))
    phi: Vec = np.linalg.lstsq(a, y, rcond=None)[0]
    return phi


def predict(phi: Vec, r_base_sensor: Vec) -> Vec:
    """(6,) the raw wrench the unknowns ``phi`` give at orientation ``R``."""
    w: Vec = design(r_base_sensor) @ phi
    return w


class ToolLoadFit(NamedTuple):
    """The least-squares fit of the tool load (SI units, sensor frame).

    mass [kg]; com: (3,) centre of mass [m] (nan without a mass); bias: (6,) the
    sensor's offset [N, N m]; mass_std, com_std: standard errors from the residuals
    (nan with too few poses); residual_force_rms / residual_torque_rms: RMS over the
    poses of the residual's norm [N, N m]; residual_force_max / residual_torque_max:
    the largest; condition: condition number of the scaled design (inf: degenerate);
    spread_deg: the largest angle between two gravity directions; poses: how many;
    undetermined: the unknowns the poses do not determine (:data:`PARAMETERS`);
    warnings: what to look at (empty: a good fit).
    """

    mass: float
    com: Vec
    bias: Vec
    mass_std: float
    com_std: Vec
    residual_force_rms: float
    residual_torque_rms: float
    residual_force_max: float
    residual_torque_max: float
    condition: float
    spread_deg: float
    poses: int
    undetermined: tuple[str, ...]
    warnings: tuple[str, ...]

    @property
    def ok(self) -> bool:
        """Every unknown is determined and the poses are well spread."""
        return not self.undetermined and self.condition <= CONDITION_WARN

    def as_dict(self) -> dict[str, Any]:
        """Plain JSON (rounded; nan and inf as None)."""
        def num(x: float, nd: int) -> float | None:
            return round(float(x), nd) if math.isfinite(x) else None

        return {
            "mass_kg": num(self.mass, 5), "com_m": [num(x, 5) for x in self.com],
            "bias": [num(x, 5) for x in self.bias],
            "mass_std_kg": num(self.mass_std, 6), "com_std_m": [num(x, 6) for x in self.com_std],
            "residual_force_rms_N": num(self.residual_force_rms, 5),
            "residual_torque_rms_Nm": num(self.residual_torque_rms, 6),
            "residual_force_max_N": num(self.residual_force_max, 5),
            "residual_torque_max_Nm": num(self.residual_torque_max, 6),
            "condition": num(self.condition, 3), "spread_deg": num(self.spread_deg, 2),
            "poses": self.poses, "undetermined": list(self.undetermined),
            "warnings": list(self.warnings), "ok": self.ok,
        }


def fit_tool_load(rotations: Sequence[Vec], wrenches: Sequence[Vec]) -> ToolLoadFit:
    """Fit bias, mass and centre of mass to raw wrenches (K, 6) [N, N m] measured at
    sensor orientations (K, 3, 3) (``R_base_sensor``) with nobody at the handle.

    Degenerate poses (:attr:`ToolLoadFit.undetermined` not empty) still give the
    minimum-norm solution, with a warning naming what it could not determine."""
    if len(rotations) != len(wrenches) or len(rotations) == 0:
        raise ValueError(f"need as many orientations as wrenches, at least one; got "
                         f"{len(rotations)} and {len(wrenches)}")
    a = _stack(rotations)
    y = np.concatenate([np.asarray(w, dtype=float).reshape(6) for w in wrenches])
    if not (np.isfinite(a).all() and np.isfinite(y).all()):
        raise ValueError("orientations and wrenches must be finite")
    u, sv, vt = np.linalg.svd(a, full_matrices=True)  # vt: all ten directions
    s = np.zeros(10)
    s[:sv.size] = sv  # (one pose has six rows: four directions unseen)
    keep = s > _RANK_TOL * s[0]
    idx = np.flatnonzero(keep)
    phi = vt[idx].T @ ((u[:, idx].T @ y) / s[idx])
    condition = float(s[0] / s[-1]) if keep.all() else math.inf
    undetermined: list[str] = []
    for v in vt[~keep]:  # directions of the unknowns the data do not see
        for i in np.flatnonzero(np.abs(v) > 0.1):
            if PARAMETERS[i] not in undetermined:
                undetermined.append(PARAMETERS[i])
    undetermined.sort(key=PARAMETERS.index)
    k = len(rotations)
    resid = (y - a @ phi).reshape(k, 6)
    rf = np.linalg.norm(resid[:, :3], axis=1)
    rt = np.linalg.norm(resid[:, 3:], axis=1)
    mass = float(phi[3] / G0)
    p = phi[7:] / G0
    dof = a.shape[0] - int(keep.sum())
    std = np.full(10, math.nan)
    if dof > 0 and keep.all():
        sigma2 = float(resid.ravel() @ resid.ravel()) / dof
        cov = (vt.T / s**2) @ vt * sigma2
        std = np.sqrt(np.maximum(np.diag(cov), 0.0))
    warnings: list[str] = []
    if undetermined:
        warnings.append("degenerate poses: their gravity directions do not determine "
                        f"{', '.join(undetermined)} (turn the wrist so that gravity "
                        "falls along different sensor axes)")
    elif condition > CONDITION_WARN:
        warnings.append(f"poorly spread poses: condition {condition:.3g} > "
                        f"{CONDITION_WARN:g} (more poses, or a larger "
                        "sensor.calibration.wrist_range)")
    if mass > MIN_MASS:
        com = p / mass
        # first order, ignoring the correlation of mass and moment
        com_std = np.sqrt((std[7:] / G0) ** 2 + (com * std[3] / G0) ** 2) / mass
    else:
        com = np.full(3, math.nan)
        com_std = np.full(3, math.nan)
        warnings.append(f"no load below the sensor (mass {mass:.4f} kg): no centre of mass")
    dirs = np.array([gravity_direction(r) for r in rotations])
    spread = float(np.degrees(np.arccos(np.clip((dirs @ dirs.T).min(), -1.0, 1.0))))
    return ToolLoadFit(mass, com, phi[[0, 1, 2, 4, 5, 6]].copy(), float(std[3] / G0), com_std,
                       float(np.sqrt(np.mean(rf**2))), float(np.sqrt(np.mean(rt**2))),
                       float(rf.max()), float(rt.max()), condition, spread, k,
                       tuple(undetermined), tuple(warnings))


# -- the poses ---------------------------------------------------------------------------

class Move:
    """A synchronised trapezoidal move from ``q_from`` to ``q_to`` (6,) [rad]: every
    joint starts and ends together; the one that travels furthest reaches ``speed``
    [rad/s] (or a triangle's peak) on ``accel`` [rad/s^2] ramps."""

    def __init__(self, q_from: Vec, q_to: Vec, speed: float, accel: float):
        self.q_from = np.asarray(q_from, dtype=float).copy()
        self.q_to = np.asarray(q_to, dtype=float).copy()
        self.delta = self.q_to - self.q_from
        self.distance = float(np.abs(self.delta).max())
        self.accel = accel
        if self.distance < 1e-9:
            self.peak, self.t_ramp, self.duration = 0.0, 0.0, 0.0
            return
        if self.distance >= speed * speed / accel:
            self.peak = speed
            self.t_ramp = speed / accel
            self.duration = self.distance / speed + self.t_ramp
        else:  # a triangle: it never reaches the speed
            self.peak = math.sqrt(self.distance * accel)
            self.t_ramp = self.peak / accel
            self.duration = 2.0 * self.t_ramp

    def at(self, t: float) -> tuple[Vec, Vec]:
        """(q_ref, qd_ref) at time ``t`` [s] since the move's start."""
        if self.duration <= 0.0 or t >= self.duration:
            return self.q_to.copy(), np.zeros(6)
        if t <= 0.0:
            return self.q_from.copy(), np.zeros(6)
        a, tr, vp, tt = self.accel, self.t_ramp, self.peak, self.duration
        if t < tr:
            s, sd = 0.5 * a * t * t, a * t
        elif t > tt - tr:
            left = tt - t
            s, sd = self.distance - 0.5 * a * left * left, a * left
        else:
            s, sd = 0.5 * a * tr * tr + vp * (t - tr), vp
        unit = self.delta / self.distance
        return self.q_from + s * unit, sd * unit


def _condition(model: RobotModel, q_a: Vec) -> float:
    return model.condition(np.concatenate((q_a, np.zeros(3))))


class Plan(NamedTuple):
    """Poses (K, 6) [rad] (the start pose first) and the speed [rad/s] of each leg:
    ``speeds[k]`` takes pose k to pose k + 1, the last one back to the start."""

    poses: list[Vec]
    speeds: list[float]
    accel: float

    def moves(self) -> list[Move]:
        """The legs, the last one back to the start pose."""
        n = len(self.poses)
        return [Move(self.poses[k], self.poses[(k + 1) % n], self.speeds[k], self.accel)
                for k in range(n)]

    def duration(self, settle_time: float, average_time: float) -> float:
        """The planned time [s]: every move, and each pose's settling and averaging."""
        return (sum(m.duration for m in self.moves())
                + len(self.poses) * (settle_time + average_time) + settle_time)


def plan_poses(model: RobotModel, q0: Vec, n: int, cal: ToolCalibrationConfig,
               limits: LimitsConfig, max_condition: float, ee_speed: float,
               ee_box: Sequence[Sequence[float]] | None = None,
               clearance: Callable[[Vec], float] | None = None,
               min_clearance: float = 0.0) -> Plan:
    """``n`` poses of the wrist from the arm pose ``q0`` (6,) (see the module docstring).

    Every pose is inside the joint limits by ``limits.position_margin``; no leg passes
    a pose whose condition number exceeds ``max_condition / 10``, nor takes the handle
    out of ``ee_box`` (``walls.ee_box``: [[x, y, z] min, max] in the base frame; not
    checked when the handle is outside it already); each leg's speed is at most
    ``cal.speed`` and ``limits.joint_velocity`` and low enough that the handle moves at
    most ``ee_speed`` [m/s]; with ``clearance`` (the robot's nearest parts' distance at
    an arm pose [m], :meth:`mmctl.model.geometry.BodyModel.closest`) no leg brings two
    of the robot's parts nearer than ``min_clearance`` (the routine's own motion is not
    braked by the self-collision check, so its plan keeps the margin).  Fewer than
    ``n`` poses come back when the range holds no more distinct orientations (the fit
    then says what is missing)."""
    q0 = np.asarray(q0, dtype=float)[:6].copy()
    box = None if ee_box is None else np.asarray(ee_box, dtype=float)
    if box is not None and not _in_box(model, q0, box):
        box = None
    lo = np.asarray(limits.joint_position_min) + limits.position_margin
    hi = np.asarray(limits.joint_position_max) - limits.position_margin
    rng = np.asarray(cal.wrist_range, dtype=float)

    def grid(half: float, count: int) -> Vec:
        return np.linspace(-half, half, count) if half > 0.0 else np.zeros(1)

    def candidates(deltas: list[tuple[float, float, float]]) -> list[Vec]:
        out = []
        for d in deltas:
            q = q0.copy()
            q[3:] += d
            if np.all(q >= lo) and np.all(q <= hi) and (box is None or _in_box(model, q, box)) \
                    and (clearance is None or clearance(q) >= min_clearance):
                out.append(q)
        return out

    def direction(q: Vec) -> Vec:
        return gravity_direction(model.fk_base(np.concatenate((q, np.zeros(3))), "sensor")
                                 .rotation)

    u0 = direction(q0)
    # probes: tilts of gravity by at most cal.probe (a fine grid, the tilt measured)
    span = np.minimum(rng, 1.5 * cal.probe)
    small = [q for q in candidates([(a, b, c) for a in grid(span[0], 7)
                                    for b in grid(span[1], 7) for c in grid(span[2], 7)])
             if math.acos(min(1.0, float(direction(q) @ u0))) <= cal.probe + 1e-9]
    large = candidates([(a, b, c) for a in grid(rng[0], 3) for b in grid(rng[1], 9)
                        for c in grid(rng[2], 13)])
    cond_max = max_condition / 10.0
    rejected: set[bytes] = set()
    for _attempt in range(8):
        chosen = [q0]
        dirs = [u0]
        for pool, count in ((small, 2), (large, n - 3)):
            pool = [q for q in pool if q.tobytes() not in rejected]
            pdirs = np.array([direction(q) for q in pool]) if pool else np.zeros((0, 3))
            for _ in range(max(count, 0)):
                if not pool:
                    break
                angle = np.arccos(np.clip(pdirs @ np.array(dirs).T, -1.0, 1.0)).min(axis=1)
                # the direction farthest from those chosen; of equals, the shorter move
                travel = np.array([np.abs(q - chosen[-1]).max() for q in pool])
                i = int(np.argmax(angle - 0.05 * travel))
                if angle[i] < _MIN_SPREAD:
                    break
                chosen.append(pool[i])
                dirs.append(pdirs[i])
        poses = _tour(chosen)
        bad = _bad_legs(model, poses, cond_max, box, clearance, min_clearance)
        if not bad:
            break
        rejected.update(poses[k].tobytes() for k in bad)
    speeds = []
    top = np.minimum(cal.speed, np.asarray(limits.joint_velocity))
    accel = min(cal.acceleration, float(np.min(limits.joint_acceleration)))
    for k in range(len(poses)):
        a, b = poses[k], poses[(k + 1) % len(poses)]
        speeds.append(_leg_speed(model, a, b, float(top.min()), ee_speed))
    return Plan(poses, speeds, accel)


def _tour(chosen: list[Vec]) -> list[Vec]:
    """The start pose, the two probes nearest first, then the rest nearest-first (a
    synchronised move takes as long as its largest joint travel)."""
    start, rest = chosen[0], chosen[1:]
    probes, others = rest[:2], rest[2:]
    out = [start]
    for group in (probes, others):
        group = list(group)
        while group:
            last = out[-1]
            i = min(range(len(group)), key=lambda j: float(np.abs(group[j] - last).max()))
            out.append(group.pop(i))
    return out


def _in_box(model: RobotModel, q_a: Vec, box: Vec) -> bool:
    p = model.fk_base(np.concatenate((q_a, np.zeros(3))), "tool").translation
    return bool(np.all(p >= box[0]) and np.all(p <= box[1]))


def _bad_legs(model: RobotModel, poses: list[Vec], cond_max: float,
              box: Vec | None, clearance: Callable[[Vec], float] | None = None,
              min_clearance: float = 0.0) -> list[int]:
    """Poses to drop: for each leg (the last one back to the start) that passes a pose
    whose condition number exceeds ``cond_max``, whose handle is outside ``box`` or
    whose parts come nearer than ``min_clearance``, the index of its end that is not
    the start pose."""
    bad = []
    n = len(poses)
    for k in range(n):
        a, b = poses[k], poses[(k + 1) % n]
        on_leg = [a + s * (b - a) for s in np.linspace(0, 1, 9)]
        if any(_condition(model, q) > cond_max or (box is not None and not _in_box(model, q, box))
               or (clearance is not None and clearance(q) < min_clearance)
               for q in on_leg):
            bad.append(k + 1 if k + 1 < n else k)
    return [k for k in bad if k != 0]


def _leg_speed(model: RobotModel, a: Vec, b: Vec, speed: float, ee_speed: float) -> float:
    """``speed``, lowered so that the handle moves at most ``ee_speed`` along the leg."""
    d = b - a
    dist = float(np.abs(d).max())
    if dist < 1e-9:
        return speed
    unit = d / dist
    worst = 0.0
    for s in np.linspace(0.0, 1.0, 9):
        jac = model.jacobian(np.concatenate((a + s * d, np.zeros(3))))
        worst = max(worst, float(np.linalg.norm(jac[:3, :6] @ unit)))
    return speed if worst * speed <= ee_speed else ee_speed / worst


# -- the routine -------------------------------------------------------------------------

class PoseSample(NamedTuple):
    """One pose weighed: q (6,) mean joints [rad]; rotation (3, 3) the sensor's axes in
    the base frame there; wrench (6,) the mean raw wrench [N, N m]; std (6,) its
    standard deviation over the samples; n: fresh samples averaged."""

    q: Vec
    rotation: Vec
    wrench: Vec
    std: Vec
    n: int


#: the routine's phases; ``done`` and ``aborted`` are final
PHASES = ("settling", "weighing", "moving", "returning", "done", "aborted")
#: what :meth:`ToolCalibration.progress` reports of a finished one until it is closed
FINISHING = "finishing"


class ToolCalibration:
    """The calibration as the daemon's loop runs it, one :meth:`step` per cycle.

    plan: the poses and leg speeds (:func:`plan_poses`; the first pose is where the arm
    is); cal: ``sensor.calibration``; prior: (mass [kg], centre of mass (3,) [m]) of
    ``sensor.wrench``, where the push check starts from; model: the loop's robot model
    (the sensor's FK); base0: (3,) the base's pose (x, y, yaw) at the start, which it
    must keep; now: the time [s] of the start (the readings' clock).

    At each pose it waits until every joint is within :data:`POSITION_TOLERANCE` and
    :data:`VELOCITY_TOLERANCE` for ``cal.settle_time``, then commands zero and averages
    ``cal.average_time`` of fresh raw samples (:attr:`samples`); between poses it
    follows :class:`Move` with position feedback; after the last pose it goes back to
    the first and ends (``done``).  Every fresh sample is compared with the wrench
    predicted by a fit of the poses weighed so far pulled toward ``prior`` (the first
    sample anchors the bias): a difference beyond ``abort_force`` / ``abort_torque``,
    the base leaving its pose, or a pose not reached within :data:`SETTLE_TIMEOUT`
    ends it ``aborted`` with :attr:`error` saying why; the caller stops the robot.
    """

    def __init__(self, plan: Plan, cal: ToolCalibrationConfig, prior: tuple[float, Vec],
                 model: RobotModel, base0: Vec, now: float):
        self.plan = plan
        self.cal = cal
        self.prior = (float(prior[0]), np.asarray(prior[1], dtype=float))
        self.model = model
        self.base0 = np.asarray(base0, dtype=float).copy()
        self.moves = plan.moves()
        self.phase = "settling"
        self.index = 0
        """The pose being approached or weighed (its index in ``plan.poses``)."""
        self.samples: list[PoseSample] = []
        self.error: str | None = None
        self.started = now
        self.finished: float | None = None
        self.peak_force = 0.0
        """The largest force difference the push check saw [N]."""
        self.peak_torque = 0.0
        self.closed = False
        """Set by the caller once it has acted on the end (the robot stopped, the fit
        stored): until then :meth:`progress` reports ``finishing``, so that whoever reads
        ``done`` or ``aborted`` there finds it all in place."""
        self._last_now = now
        self._tau = 0.0  # the motion's clock [s]: stands while the arm's pose is stale,
        # runs at the arm's speed scaling
        self._t0 = 0.0  # when the current phase began, on that clock
        self._t0_now = now  # and on the readings' clock (settling and weighing)
        self._still_since: float | None = None
        self._move: Move | None = None
        self._last_seq: int | None = None
        self._checked_seq: int | None = None  # the last sample the push check saw
        self._checked_at = now  # when the push check last passed
        # the smallest now - pose_time [s] of this and the last LAG_WINDOW (two buckets:
        # a clock that drifts, as a simulated controller's under load, is followed)
        self._lag_bucket = (math.nan, math.inf, math.inf)  # (start, this, last)
        self._phi: Vec | None = None
        self._acc: list[Vec] = []
        self._acc_q: list[Vec] = []
        self._zero = np.zeros(6)

    @property
    def running(self) -> bool:
        return self.phase not in ("done", "aborted")

    @property
    def target(self) -> Vec:
        """The pose the arm is heading to or resting at."""
        pose: Vec = self.plan.poses[self.index]
        return pose

    def abort(self, reason: str, now: float | None = None) -> None:
        """End it (the caller stops the robot); a finished routine stays as it ended."""
        if self.running:
            self.phase = "aborted"
            self.error = reason
            self.finished = self._last_now if now is None else now

    def progress(self) -> dict[str, Any]:
        """Plain JSON: phase (``finishing`` while the caller has not :attr:`closed` a
        finished one), pose (1-based) of poses, poses weighed, seconds elapsed, error."""
        end = self.finished if self.finished is not None else self._last_now
        phase = self.phase if self.running or self.closed else FINISHING
        return {"phase": phase, "pose": self.index + 1, "poses": len(self.plan.poses),
                "weighed": len(self.samples), "elapsed_s": round(end - self.started, 3),
                "error": self.error}

    def step(self, q: Vec, qd: Vec, raw: Vec, sequence: int, now: float,
             hold: bool = False, scaling: float = 1.0, pose_new: bool = True,
             sample_age: float = 0.0, pose_time: float | None = None) -> Vec:
        """One cycle: measured ``q``, ``qd`` (9,) (arm, base), the raw wrench (6,) and
        its ``sequence``, ``now`` [s]; ``hold``: the arm's pose is stale (command zero,
        the motion's clock stands); ``scaling``: the share of a commanded speed the arm
        executes (the UR's speed slider: the motion's clock runs that much slower, so
        the reference waits for the arm); ``pose_new``: ``q`` is this cycle's sample
        (False: one repeated from an earlier cycle); ``sample_age``: how old the wrench
        is [s] (``now`` less its reception); ``pose_time``: the arm controller's time
        stamp of ``q`` [s, its own clock] (None: not known).  Returns the arm's velocity
        command (6,) [rad/s] (zero once it is no longer :attr:`running`).

        The push check compares a wrench with a pose of its time only: a new pose, and a
        pair whose skew (the later of the two's delays, at most :data:`CHECK_SKEW`) times
        the fastest joint's speed is at most :data:`CHECK_ANGLE`.  Else the wrist has
        turned between the two (at 1 rad/s, 0.5 s of a starved loop's repeated poses or
        of a starved sensor link's late sample turn the handle's weight into a 5-8 N
        "push": both seen in CI runs under load); the check waits for the next pair
        (both stream at the loop's rate).  A pose that is new to the loop can still be
        late: a starved arm link draining a backlog hands over one old sample per
        cycle.  Its lag
        (``now - pose_time``) is judged against the smallest of the last seconds
        (:data:`LAG_WINDOW`; the controller's clock and ours differ by a near constant,
        which the smallest lag takes out), and counts in the skew.  Without a checked
        pair for :data:`UNCHECKED_HOLD` the arm is held (zero command, the motion's clock
        stands: a still wrist makes any fresh pair checkable) until one comes; after
        :data:`SETTLE_TIMEOUT` without one the routine aborts."""
        dt = max(now - self._last_now, 0.0)
        self._last_now = now
        if not self.running:
            return self._zero
        base = np.asarray(q[6:9], dtype=float)
        moved = float(np.hypot(*(base[:2] - self.base0[:2])))
        turned = abs(math.remainder(float(base[2] - self.base0[2]), 2.0 * math.pi))
        if moved > BASE_TOLERANCE[0] or turned > BASE_TOLERANCE[1]:
            self.abort(f"the base moved ({moved:.3f} m, {turned:.3f} rad) during the "
                       "calibration: it must stand still", now)
            return self._zero
        r = self.model.fk_base(q, "sensor").rotation
        fresh = sequence != self._last_seq
        self._last_seq = sequence
        q_a = np.asarray(q[:6], dtype=float)
        qd_a = np.asarray(qd[:6], dtype=float)
        skew = sample_age
        if pose_time is not None and math.isfinite(pose_time):
            lag = now - pose_time
            skew = max(skew, lag - self._lag_floor(lag, now))
        timely = pose_new and skew <= CHECK_SKEW \
            and skew * float(np.abs(qd_a).max()) <= CHECK_ANGLE
        if timely and sequence != self._checked_seq:
            self._checked_seq = sequence
            if not self._check(raw, r, now):
                return self._zero
            self._checked_at = now
        unchecked = now - self._checked_at
        if unchecked > SETTLE_TIMEOUT:
            self.abort(f"the push check found no arm pose and wrench sample of the same "
                       f"time for {unchecked:.1f} s (at pose {self.index + 1}): the "
                       "machine is too busy to calibrate safely", now)
            return self._zero
        if hold or unchecked > UNCHECKED_HOLD:
            return self._zero
        self._tau += dt * min(max(scaling, 0.0), 1.0) if math.isfinite(scaling) else 0.0
        if self.phase in ("moving", "returning"):
            assert self._move is not None
            t = self._tau - self._t0
            q_ref, qd_ref = self._move.at(t)
            if t >= self._move.duration:
                self._enter("settling")
            return self._clip(qd_ref + GAIN * (q_ref - q_a))
        if self.phase == "settling":
            err = self.target - q_a
            if np.abs(err).max() < POSITION_TOLERANCE and np.abs(qd_a).max() < VELOCITY_TOLERANCE:
                if self._still_since is None:
                    self._still_since = now
                if now - self._still_since >= self.cal.settle_time:
                    if self._returned():
                        self.phase = "done"
                        self.finished = now
                        return self._zero
                    self._enter("weighing")
                    return self._zero
            else:
                self._still_since = None
            if now - self._t0_now > SETTLE_TIMEOUT + self.cal.settle_time:
                worst = int(np.argmax(np.abs(err)))
                self.abort(f"pose {self.index + 1} not reached within "
                           f"{SETTLE_TIMEOUT + self.cal.settle_time:g} s (joint {worst} "
                           f"{float(err[worst]):+.4f} rad off)", now)
                return self._zero
            return self._clip(GAIN * err)
        if self.phase == "weighing":
            if fresh:
                self._acc.append(np.asarray(raw, dtype=float).copy())
                self._acc_q.append(q_a.copy())
            if now - self._t0_now >= self.cal.average_time and len(self._acc) >= MIN_SAMPLES:
                self._record()
                self._next()
            elif now - self._t0_now > self.cal.average_time + SETTLE_TIMEOUT:
                self.abort(f"only {len(self._acc)} fresh sensor samples in "
                           f"{now - self._t0_now:.1f} s at pose {self.index + 1}", now)
            return self._zero
        return self._zero

    # -- helpers -------------------------------------------------------------------------

    def _lag_floor(self, lag: float, now: float) -> float:
        """The smallest pose lag over the last one to two :data:`LAG_WINDOW` (``lag``
        included)."""
        start, this, last = self._lag_bucket
        if not now - start < LAG_WINDOW:  # (nan at first)
            start, last, this = now, this, math.inf
        this = min(this, lag)
        self._lag_bucket = (start, this, last)
        return min(this, last)

    def _check(self, raw: Vec, r: Vec, now: float) -> bool:
        """The push check on a fresh sample; False (and aborted) on a hand."""
        if self._phi is None:  # the first sample anchors the bias
            self._phi = solve([r], [raw], self.prior)
        d = np.asarray(raw, dtype=float) - predict(self._phi, r)
        f = float(np.linalg.norm(d[:3]))
        t = float(np.linalg.norm(d[3:]))
        self.peak_force = max(self.peak_force, f)
        self.peak_torque = max(self.peak_torque, t)
        if f > self.cal.abort_force or t > self.cal.abort_torque:
            self.abort(f"{f:.1f} N / {t:.2f} N m on the handle beyond its weight "
                       f"(sensor.calibration.abort_force {self.cal.abort_force:g} N, "
                       f"abort_torque {self.cal.abort_torque:g} N m) during "
                       f"{self.phase} at pose {self.index + 1}: hands off the handle", now)
            return False
        return True

    def _clip(self, cmd: Vec) -> Vec:
        top = self.plan.speeds[self.index - 1] if self.phase in ("moving", "returning") \
            else max(self.plan.speeds)
        out: Vec = np.clip(cmd, -top, top)
        return out

    def _enter(self, phase: str) -> None:
        self.phase = phase
        self._t0 = self._tau
        self._t0_now = self._last_now
        self._still_since = None

    def _returned(self) -> bool:
        return self.index == 0 and len(self.samples) == len(self.plan.poses)

    def _record(self) -> None:
        w = np.array(self._acc)
        q_mean = np.mean(self._acc_q, axis=0)
        r = self.model.fk_base(np.concatenate((q_mean, np.zeros(3))), "sensor").rotation
        self.samples.append(PoseSample(q_mean, r, w.mean(axis=0), w.std(axis=0), len(w)))
        self._acc, self._acc_q = [], []
        self._phi = solve([s.rotation for s in self.samples], [s.wrench for s in self.samples],
                          self.prior)

    def _next(self) -> None:
        """After weighing pose ``index``: on to the next pose, or back to the start."""
        self._move = self.moves[self.index]
        nxt = (self.index + 1) % len(self.plan.poses)
        self._enter("moving" if nxt else "returning")
        self.index = nxt
