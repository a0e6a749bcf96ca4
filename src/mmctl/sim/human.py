"""A simulated person doing the paper's peg-in-hole task with the handle.

The hand is an impedance (stiffness K [N/m], damping D [N s/m]) attached to a moving
reference point ``x_r`` that the person plans:

    f = K (x_r - x) + D (ẋ_r - ẋ),   ||f|| <= f_max

``x``/``ẋ`` are the handle point's observed position/velocity in the world frame.  The
reference follows a plan built from the :class:`Task` (a list of holes): for each hole,
*react* (reaction time), *reach* the approach point above the hole along a
minimum-jerk path at the person's speed, wait until the handle has *settled* there,
react, *insert* along the hole axis (minimum-jerk, slower), settle, *dwell* (hold the
peg in), then *extract* back to the approach point.  The task ends when the dwell in
the last hole ends: that instant is ``T_f``.

Effort build-up: once the plan has arrived, a person whose handle stops short of the
goal pushes harder until it gets there: the hand's equilibrium point moves on along the
remaining gap, ``ẋ_e = (x_goal - x) / t_r`` with ``t_r`` the person's reaction time (one
correction per reaction time), reset at every new move.  Without it a dead band in the
robot's wrench pipeline (SPEC §1: the robot ignores pushes below ``deadband_force``)
stops the handle where ``K |x_r - x|`` falls under the dead band, short of the
insertion tolerance, and the person would wait forever.

Effort regulation: a person does not pull arbitrarily hard on a handle that lags.  The
minimum-jerk phase advances at ``g(||f||) / T`` with ``g = 1`` below the comfortable
force ``f_comfort`` and falling linearly to 0 at ``f_max``; a robot that follows
poorly therefore slows the person down (longer ``T_f``, higher mean force).

Switching policy (always running; see :class:`SwitchPolicy`): the person wants
*locomotion* when the next hole lies beyond their comfortable reach from the arm's
mount (or when the handle stalls against the arm's workspace), and *manipulation* back
once the handle is near the hole; a request is emitted ``decision_delay`` after the
wish arises.  The model takes no mode: requests only matter when the controller runs
the switch strategy, so the same person faces every approach.

Everything is deterministic; :meth:`SimulatedHuman.update` is one call per control
cycle (or slower: it integrates with the time since the previous call).
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

Vec = NDArray[np.float64]


def min_jerk(s: float) -> tuple[float, float, float]:
    """Minimum-jerk profile σ(s) = 10s³ − 15s⁴ + 6s⁵ and its derivatives σ', σ'' for
    the normalised time s ∈ [0, 1] (clamped): σ(0) = 0, σ(1) = 1, σ' = σ'' = 0 at both ends."""
    s = min(max(s, 0.0), 1.0)
    s2 = s * s
    sig = s2 * s * (10.0 - 15.0 * s + 6.0 * s2)
    dsig = 30.0 * s2 * (1.0 - s) * (1.0 - s)
    ddsig = 60.0 * s * (1.0 - s) * (1.0 - 2.0 * s)
    return sig, dsig, ddsig


@dataclass(frozen=True)
class HumanParams:
    """One person (SI units).  Defaults are a median user."""

    stiffness: float = 350.0  # hand stiffness K [N/m]
    damping: float = 30.0  # hand damping D [N s/m]
    speed: float = 0.25  # mean speed of a reach [m/s] (min-jerk peak = 1.875x)
    insertion_speed: float = 0.08  # mean speed of insertion/extraction [m/s]
    min_move_time: float = 0.6  # shortest planned movement [s]
    reaction_time: float = 0.30  # delay between noticing "done" and the next move [s]
    dwell_time: float = 0.5  # peg held in the hole [s]
    position_tolerance: float = 0.015  # settled at an approach point [m]
    insertion_tolerance: float = 0.005  # settled at the bottom of a hole [m]
    settle_speed: float = 0.05  # settled: handle slower than this [m/s]
    f_comfort: float = 40.0  # force above which the person slows the plan [N]
    f_max: float = 70.0  # force at which the plan stops (and the force saturates) [N]
    comfort_reach: float = 0.90  # switch policy: comfortable horizontal reach from the arm mount [m]
    near_distance: float = 0.25  # switch policy: back to manipulation this close to the hole [m]
    decision_delay: float = 0.6  # switch policy: wish -> button press [s]
    stall_time: float = 0.6  # switch policy: stalled this long in manipulation -> locomotion [s]

    def __post_init__(self) -> None:
        for name in ("stiffness", "speed", "insertion_speed", "min_move_time", "f_comfort",
                     "position_tolerance", "insertion_tolerance", "settle_speed",
                     "comfort_reach", "near_distance"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"HumanParams.{name} = {getattr(self, name)}: must be > 0")
        for name in ("damping", "reaction_time", "dwell_time", "decision_delay", "stall_time"):
            if getattr(self, name) < 0.0:
                raise ValueError(f"HumanParams.{name} = {getattr(self, name)}: must be >= 0")
        if not self.f_max > self.f_comfort:
            raise ValueError(f"HumanParams.f_max = {self.f_max}: must be > f_comfort = {self.f_comfort}")


@dataclass(frozen=True)
class Hole:
    """A hole, as handle positions (world frame [m]): ``approach`` (3,) where the peg is
    aligned with the hole, ``bottom`` (3,) where the handle is with the peg fully in."""

    approach: tuple[float, float, float]
    bottom: tuple[float, float, float]


@dataclass(frozen=True)
class Task:
    """The holes to fill, in order, and the arm mount offset the person judges reach
    from (in the base frame, x and y [m])."""

    holes: tuple[Hole, ...]
    arm_mount_xy: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if not self.holes:
            raise ValueError("a task needs at least one hole")


#: Hole layout of the study (in the task plane, metres from the start handle position;
#: first coordinate along the robot's forward axis at the start, second to its left).
#: Two holes are within the arm's reach of the start pose (0.4-0.8 m from the arm's
#: mount), three beyond it (1.2-1.8 m); the moves are 0.3-1.8 m, the last one 0.4 m.
STUDY_HOLES: tuple[tuple[float, float], ...] = (
    (0.20, 0.25), (-0.15, -0.30), (0.30, 1.45), (-0.10, 1.05), (0.20, 0.75),
)
#: The short task of ``--quick``: one hole in reach, one beyond.
QUICK_HOLES: tuple[tuple[float, float], ...] = ((0.15, 0.20), (0.10, 1.10))


def peg_in_hole_task(
    start: ArrayLike,
    axis: ArrayLike,
    heading: float,
    holes_uv: tuple[tuple[float, float], ...] = STUDY_HOLES,
    depth: float = 0.06,
    arm_mount_xy: tuple[float, float] = (0.0, 0.0),
) -> Task:
    """Lay out holes in the plane through ``start`` (3,) orthogonal to the insertion
    ``axis`` (3,) (the peg's direction at the start, world frame).

    ``holes_uv`` are offsets [m] along ``u`` (the robot's heading ``heading`` [rad]
    projected on the plane; if the axis is horizontal, world up) and ``w = axis × u``.
    Approach points lie in the plane; bottoms are ``depth`` [m] further along ``axis``.
    """
    p0 = np.asarray(start, dtype=float)
    n = np.asarray(axis, dtype=float)
    n = n / np.linalg.norm(n)
    fwd = np.array([math.cos(heading), math.sin(heading), 0.0])
    u = fwd - n * (fwd @ n)
    if np.linalg.norm(u) < 0.3:  # axis close to the heading (a wall ahead): use world up
        up = np.array([0.0, 0.0, 1.0])
        u = up - n * (up @ n)
    u = u / np.linalg.norm(u)
    w = np.cross(n, u)
    if w @ np.array([-math.sin(heading), math.cos(heading), 0.0]) < 0.0:
        w = -w  # second coordinate to the robot's left
    holes = []
    for a, b in holes_uv:
        ap = p0 + a * u + b * w
        bt = ap + depth * n
        holes.append(Hole(tuple(float(c) for c in ap), tuple(float(c) for c in bt)))  # type: ignore[arg-type]
    return Task(tuple(holes), arm_mount_xy)


class Phase(enum.Enum):
    """What the person is doing."""

    REACT = "react"
    REACH = "reach"
    INSERT = "insert"
    DWELL = "dwell"
    EXTRACT = "extract"
    DONE = "done"


class HandleObservation(NamedTuple):
    """What the person perceives each cycle (world frame).

    t: time [s]; position, velocity: (3,) handle point [m], [m/s];
    base: (3,) base pose x, y [m], yaw [rad].
    """

    t: float
    position: Vec
    velocity: Vec
    base: Vec


class HumanAction(NamedTuple):
    """What the person does: ``force`` (3,) on the handle, world frame [N] (no torque: the
    task keeps the orientation); ``switch_request`` "locomotion"/"manipulation" or None;
    ``phase``; ``done`` once the last insertion is finished."""

    force: Vec
    switch_request: str | None
    phase: Phase
    done: bool


@dataclass
class _Segment:
    phase: Phase
    hole: int
    target: Vec | None = None  # moves: where to
    speed: float = 0.0  # moves [m/s]
    tol: float = 0.0  # moves: settle tolerance [m]
    duration: float = 0.0  # holds [s]


def _plan(task: Task, p: HumanParams, loop: bool) -> list[_Segment]:
    segs: list[_Segment] = []
    last = len(task.holes) - 1
    for i, h in enumerate(task.holes):
        ap, bt = np.array(h.approach), np.array(h.bottom)
        segs += [
            _Segment(Phase.REACT, i, duration=p.reaction_time),
            _Segment(Phase.REACH, i, ap, p.speed, p.position_tolerance),
            _Segment(Phase.REACT, i, duration=p.reaction_time),
            _Segment(Phase.INSERT, i, bt, p.insertion_speed, p.insertion_tolerance),
            _Segment(Phase.DWELL, i, duration=p.dwell_time),
        ]
        if i < last or loop:
            segs.append(_Segment(Phase.EXTRACT, i, ap, p.insertion_speed, p.position_tolerance))
    return segs


class SwitchPolicy:
    """When the person asks for locomotion or manipulation (see module doc).

    ``want`` is the person's current wish; it starts as "manipulation" (what the
    switch strategy starts in).  One locomotion phase per far hole: after returning to
    manipulation near a hole, only a stall asks for locomotion again for that hole.
    """

    def __init__(self, params: HumanParams, arm_mount_xy: tuple[float, float] = (0.0, 0.0)) -> None:
        self.params = params
        self.arm_mount_xy = arm_mount_xy
        self.want = "manipulation"
        self._since: float | None = None
        self._returned_for = -1
        self._stalled_since: float | None = None

    def update(self, t: float, hole: int, goal: Vec, handle: Vec, base: Vec, stalled: bool) -> str | None:
        """One decision at time ``t`` [s] toward ``goal`` (3,) of hole index ``hole``."""
        p = self.params
        c, s = math.cos(base[2]), math.sin(base[2])
        mx = base[0] + c * self.arm_mount_xy[0] - s * self.arm_mount_xy[1]
        my = base[1] + s * self.arm_mount_xy[0] + c * self.arm_mount_xy[1]
        reach = math.hypot(goal[0] - mx, goal[1] - my)
        if stalled:
            self._stalled_since = t if self._stalled_since is None else self._stalled_since
        else:
            self._stalled_since = None
        if self.want == "manipulation":
            stuck = self._stalled_since is not None and t - self._stalled_since >= p.stall_time
            wish = (reach > p.comfort_reach and self._returned_for != hole) or stuck
        else:
            gap = goal - handle
            wish = math.sqrt(float(gap @ gap)) < p.near_distance
        if not wish:
            self._since = None
            return None
        if self._since is None:
            self._since = t
        if t - self._since < p.decision_delay:
            return None
        self._since = None
        self._stalled_since = None
        if self.want == "manipulation":
            self.want = "locomotion"
        else:
            self.want = "manipulation"
            self._returned_for = hole
        return self.want


class SimulatedHuman:
    """The person: plan, hand impedance, effort regulation and switching policy.

    ``loop=True`` restarts the task after the last hole (for a live demo); then
    ``done`` never becomes true.  ``finish_time`` is ``T_f`` [s] once done.
    Nothing here knows which control approach runs the robot.
    """

    def __init__(self, params: HumanParams, task: Task, loop: bool = False) -> None:
        self.params = params
        self.task = task
        self.loop = loop
        self.finish_time: float | None = None
        self._segs = _plan(task, params, loop)
        self._policy = SwitchPolicy(params, task.arm_mount_xy)
        self._goals = [np.array(h.approach) for h in task.holes]
        self._k = 0
        self._t: float | None = None
        self._t_seg = 0.0
        self._s = 0.0
        self._move_time = 1.0
        self._x0 = np.zeros(3)
        self._ref = np.zeros(3)
        self._ref_vel = np.zeros(3)
        self._arrived = False
        self._rate = 1.0
        self._effort = np.zeros(3)  # effort build-up: equilibrium shift [m]

    @property
    def phase(self) -> Phase:
        """The current phase."""
        return Phase.DONE if self._k >= len(self._segs) else self._segs[self._k].phase

    @property
    def hole(self) -> int:
        """Index of the hole being worked on."""
        return self._segs[min(self._k, len(self._segs) - 1)].hole

    @property
    def wants(self) -> str:
        """The mode the person currently wants (their switching policy's state)."""
        return self._policy.want

    def _enter(self, t: float) -> None:
        """Start segment ``self._k`` at time ``t`` [s] from the current reference."""
        self._t_seg = t
        self._s = 0.0
        self._arrived = False
        self._ref_vel = np.zeros(3)
        self._effort = np.zeros(3)
        if self._k >= len(self._segs) and self.loop:
            self._k = 0
        if self._k < len(self._segs):
            seg = self._segs[self._k]
            if seg.target is not None:
                self._x0 = self._ref.copy()
                d = float(np.linalg.norm(seg.target - self._x0))
                self._move_time = max(self.params.min_move_time, d / seg.speed)

    def _advance(self, t: float, dt: float, x: Vec, xd: Vec) -> None:
        """Move the plan forward to time ``t`` [s] (``dt`` since the previous call)."""
        p = self.params
        while self._k < len(self._segs):
            seg = self._segs[self._k]
            if seg.target is None:  # a hold: react or dwell
                if t - self._t_seg < seg.duration:
                    return
                if seg.phase is Phase.DWELL and self._k == len(self._segs) - 1:
                    self.finish_time = self._t_seg + seg.duration
                self._k += 1
                self._enter(t)
                continue
            if not self._arrived:  # a minimum-jerk move, paced by the effort
                self._s = min(1.0, self._s + dt * self._rate / self._move_time)
                sig, dsig, _ = min_jerk(self._s)
                span = seg.target - self._x0
                self._ref = self._x0 + sig * span
                self._ref_vel = span * (dsig * self._rate / self._move_time)
                if self._s >= 1.0:
                    self._arrived = True
                    self._ref = seg.target.copy()
                    self._ref_vel = np.zeros(3)
                return
            gap = seg.target - x  # reference arrived: wait until the handle settles
            if gap @ gap < seg.tol * seg.tol and xd @ xd < p.settle_speed * p.settle_speed:
                self._k += 1
                self._enter(t)
                continue
            if self._rate > 0.0:  # not saturated: push harder toward the goal
                rt = p.reaction_time
                self._effort += gap * (min(1.0, dt / rt) if rt > 0.0 else 1.0)
            return

    def update(self, obs: HandleObservation) -> HumanAction:
        """One step at ``obs.t`` [s]: advance the plan, return the hand's force on the
        handle and any switch request.  The first call fixes the start (reference =
        handle position)."""
        p = self.params
        x = np.asarray(obs.position, dtype=float)
        xd = np.asarray(obs.velocity, dtype=float)
        t = float(obs.t)
        if self._t is None:
            self._t = t
            self._ref = x.copy()
            self._enter(t)
        dt = max(0.0, t - self._t)
        self._t = t
        self._advance(t, dt, x, xd)
        err = self._ref - x
        force = p.stiffness * (err + self._effort) + p.damping * (self._ref_vel - xd)
        mag = math.sqrt(float(force @ force))
        if mag > p.f_max:
            force *= p.f_max / mag
        self._rate = min(1.0, max(0.0, (p.f_max - mag) / (p.f_max - p.f_comfort)))
        done = self._k >= len(self._segs)
        request = None
        if not done:
            seg = self._segs[self._k]
            stalled = (seg.target is not None and float(xd @ xd) < p.settle_speed ** 2
                       and float(err @ err) > (3.0 * p.position_tolerance) ** 2)
            request = self._policy.update(t, seg.hole, self._goals[seg.hole], x,
                                          np.asarray(obs.base, dtype=float), stalled)
        return HumanAction(force, request, self.phase, done)
