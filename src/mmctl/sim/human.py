"""A simulated person doing the paper's peg-in-hole task with the handle.

The hand is an impedance (stiffness K [N/m], damping D [N s/m]) attached to a moving
reference point ``x_r`` that the person plans:

    f = K (x_r - x) + D (ẋ_r - ẋ),   ||f|| <= f_max

``x``/``ẋ`` are the handle point's observed position/velocity in the world frame.  The
reference follows a plan built from the :class:`Task` (a list of holes): for each hole,
*react* (reaction time), *reach* the approach point in front of the hole along a
minimum-jerk path at the person's speed, wait until the handle has *settled* there,
react, *insert* along the hole axis (minimum-jerk, slower), settle, *dwell* (hold the
peg in), then *extract* back to the approach point.  The task ends when the dwell in
the last hole ends: that instant is ``T_f``.  Then the person *holds* the peg in the
last hole for ``hold_time`` (the end-of-trial hold; x_f is read at both ends of it).

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

Motor noise (signal-dependent, Harris & Wolpert 1998): the force the hand applies is
``f (1 + cv η)`` per axis, i.e. ``f + cv ||f|| η`` with ``η`` (3,) a unit-variance
low-pass (Ornstein-Uhlenbeck) process of corner frequency ``noise_corner``: the standard
deviation grows in proportion to the force, zero with the hand at rest.  ``η`` comes
from the person's own generator (``noise_seed``), one draw per :meth:`SimulatedHuman.update`,
so the noise at a given instant depends on the person and the time only.

Switching policy (always running; see :class:`SwitchPolicy`): the person wants
*locomotion* when the next hole lies beyond their comfortable reach from the arm's
mount (or when the handle stalls against the arm's workspace), and *manipulation* back
once the handle is near the hole; the button is pressed ``decision_delay`` after the
wish arises.  The press costs time: the person's plan pauses for ``press_time``
(thumb press) and the request is sent when the press ends.  A handle without a mode
button (``button=False``: the paper's locomotion and min-energy conditions offer no
switching) is never pressed.  The model takes no mode: the same person faces every
approach.

Everything is deterministic; :meth:`SimulatedHuman.update` is one call per control
cycle (or slower: it integrates with the time since the previous call).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Sequence
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
    """One person (SI units).  Defaults are a median user (docs/study.md: sources)."""

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
    #: End-of-trial hold [s]: the peg stays in the last hole this long after T_f.  3 s =
    #: three time constants of the paper's null-space gain G = 1 s^-1 (a first-order
    #: return to q_des would be 95 % done): long enough to see where the arm settles.
    hold_time: float = 3.0
    #: Pressing the mode button [s]: the plan pauses this long.  Card, Moran & Newell
    #: (1980), keystroke-level model, operator K: 0.20 s (average skilled typist) to
    #: 0.28 s (average non-secretary typist); the population draws in that range.
    press_time: float = 0.24
    #: Signal-dependent force noise: coefficient of variation (SD / mean force) per axis.
    #: Young adults' steady submaximal force: CV 4.1-4.5 % +- 3.1 % (Baweja et al. 2009,
    #: Exp Brain Res 197:35, index finger, 2-70 % MVC); SD proportional to the force
    #: (Harris & Wolpert 1998; Jones, Hamilton & Wolpert 2002).
    force_cv: float = 0.04
    #: Corner frequency of the noise [Hz]: the fluctuations of a steady contraction's
    #: force are low-frequency oscillations, mostly below 1-2 Hz (Fox et al. 2013, PLoS
    #: ONE, "Modulation of force below 1 Hz"; Slifkin & Newell 1999, power spectra).
    noise_corner: float = 2.0

    def __post_init__(self) -> None:
        for name in ("stiffness", "speed", "insertion_speed", "min_move_time", "f_comfort",
                     "position_tolerance", "insertion_tolerance", "settle_speed",
                     "comfort_reach", "near_distance", "noise_corner"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"HumanParams.{name} = {getattr(self, name)}: must be > 0")
        for name in ("damping", "reaction_time", "dwell_time", "decision_delay", "stall_time",
                     "hold_time", "press_time", "force_cv"):
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
class Plane:
    """A plane through ``point`` (3,) [m] with unit ``normal`` (3,), world frame."""

    point: tuple[float, float, float]
    normal: tuple[float, float, float]


@dataclass(frozen=True)
class Task:
    """The holes to fill, in order, and the arm mount offset the person judges reach
    from (in the base frame, x and y [m]).  ``surface``: the plane of the approach
    points, its normal pointing out of the holes (toward the robot): for the wall task
    the wall's face as the handle meets it (the peg's length in front of the wall)."""

    holes: tuple[Hole, ...]
    arm_mount_xy: tuple[float, float] = (0.0, 0.0)
    surface: Plane | None = None

    def __post_init__(self) -> None:
        if not self.holes:
            raise ValueError("a task needs at least one hole")


#: Hole layout of the board task (``--task board``; and the live demo's, ``mmctl run``):
#: in the task plane, metres from the start handle position; first coordinate along the
#: robot's forward axis at the start, second to its left.  Two holes are within the
#: arm's reach of the start pose (0.4-0.8 m from the arm's mount), three beyond it
#: (1.2-1.8 m); the moves are 0.3-1.8 m, the last one 0.4 m.  Invented (not the paper's).
STUDY_HOLES: tuple[tuple[float, float], ...] = (
    (0.20, 0.25), (-0.15, -0.30), (0.30, 1.45), (-0.10, 1.05), (0.20, 0.75),
)
#: The short board task of ``--quick --task board``: one hole in reach, one beyond.
QUICK_HOLES: tuple[tuple[float, float], ...] = ((0.15, 0.20), (0.10, 1.10))

#: Depth of every hole [m]: how far the peg goes in.
HOLE_DEPTH = 0.06


def peg_in_hole_task(
    start: ArrayLike,
    axis: ArrayLike,
    heading: float,
    holes_uv: tuple[tuple[float, float], ...] = STUDY_HOLES,
    depth: float = HOLE_DEPTH,
    arm_mount_xy: tuple[float, float] = (0.0, 0.0),
) -> Task:
    """The board task: holes in the plane through ``start`` (3,) orthogonal to the
    insertion ``axis`` (3,) (the peg's direction at the start, world frame).

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
        holes.append(Hole(_t3(ap), _t3(bt)))
    return Task(tuple(holes), arm_mount_xy, Plane(_t3(p0), _t3(-n)))


def _t3(v: Vec) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


#: The wall task needs the peg horizontal: |sin(elevation)| of the insertion axis at
#: most this (5 deg: the handle's orientation is held, so a tilt stays all trial long).
WALL_AXIS_TOLERANCE = math.sin(math.radians(5.0))


def wall_task(
    start: ArrayLike,
    axis: ArrayLike,
    holes_wz: Sequence[tuple[float, float]],
    standoff: float,
    depth: float = HOLE_DEPTH,
    arm_mount_xy: tuple[float, float] = (0.0, 0.0),
) -> Task:
    """The paper's task: holes in a vertical wall ahead of the peg, insertion along the
    wall's normal (the peg orthogonal to the wall, horizontal).

    ``start`` (3,): the handle at the start [m]; ``axis`` (3,): the peg's direction
    there (the tool z axis, world frame; horizontal within 5 deg, else ValueError),
    which is the wall's inward normal.  The approach points lie in the vertical plane
    ``standoff`` [m] ahead of ``start`` along ``axis``; hole ``(w, z)`` is ``w`` [m]
    to the left of ``start`` along the wall (left of the peg's direction) at height
    ``z`` [m] above the floor; its bottom is ``depth`` [m] further along ``axis``.
    """
    p0 = np.asarray(start, dtype=float)
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    if abs(a[2]) > WALL_AXIS_TOLERANCE:
        raise ValueError(f"the wall task needs a horizontal peg: the tool z axis {a.round(3)} "
                         f"is {math.degrees(math.asin(min(1.0, abs(a[2])))):.1f} deg from "
                         "horizontal (at most 5)")
    if standoff < 0.0 or depth <= 0.0:
        raise ValueError(f"wall task: standoff = {standoff} m must be >= 0 and depth = "
                         f"{depth} m > 0")
    n = np.array([a[0], a[1], 0.0])
    n /= np.linalg.norm(n)  # exactly horizontal: the wall is vertical
    left = np.array([-n[1], n[0], 0.0])  # up x n
    face = p0 + standoff * n
    holes = []
    for w, z in holes_wz:
        ap = face + w * left
        ap[2] = z
        holes.append(Hole(_t3(ap), _t3(ap + depth * n)))
    return Task(tuple(holes), arm_mount_xy, Plane(_t3(face), _t3(-n)))


@dataclass(frozen=True)
class WallFamily:
    """A family of wall layouts, one drawn per study seed (:func:`draw_wall_layout`).

    holes: (min, max) hole count, uniform; near_edge, far_edge: (low, high) [m] of the
    uniform draws of the layout's two ends along the wall (lateral offset w from the
    start handle, positive to the robot's left); heights: (low, high) [m] above the
    floor, uniform; standoff: approach plane ahead of the start handle [m]; depth: the
    holes' depth [m].  The holes split [near, far] into equal strata, one hole in each
    (at least 40 % of a stratum apart); one hole, drawn, is at the start handle's
    height; the order of visits is a drawn permutation.  docs/study.md gives the
    reasons for every default.
    """

    #: around the board layout's 5 (the paper gives no count)
    holes: tuple[int, int] = (4, 6)
    #: the first holes within the arm's reach, a little to the right of the start
    near_edge: tuple[float, float] = (-0.5, -0.2)
    #: beyond the UR10e's 1.3 m reach (UR data sheet), so every layout needs the base
    #: (SPEC §4: holes spread wider than the arm's reach); a wall a few steps long
    far_edge: tuple[float, float] = (1.3, 2.0)
    #: between a median adult's knuckle height (~0.75 m) and a median woman's shoulder
    #: height (~1.3 m) (Pheasant & Haslegrave, Bodyspace): pushing a handle without
    #: stooping or lifting the arm above the shoulder; +-0.25 m about the wall pose's
    #: 1.05 m handle, which the arm alone must reach
    heights: tuple[float, float] = (0.80, 1.30)
    #: the robot parked with the peg 10 cm clear of the wall
    standoff: float = 0.10
    depth: float = HOLE_DEPTH

    def __post_init__(self) -> None:
        lo, hi = self.holes
        if not 1 <= lo <= hi:
            raise ValueError(f"WallFamily.holes = {self.holes}: need 1 <= min <= max")
        for name in ("near_edge", "far_edge", "heights"):
            a, b = getattr(self, name)
            if not a <= b:
                raise ValueError(f"WallFamily.{name} = {(a, b)}: need low <= high")
        if not self.near_edge[1] < self.far_edge[0]:
            raise ValueError(f"WallFamily: near_edge {self.near_edge} must lie below "
                             f"far_edge {self.far_edge}")
        if self.heights[0] <= 0.0 or self.standoff < 0.0 or self.depth <= 0.0:
            raise ValueError("WallFamily: heights must be > 0 m, standoff >= 0 m, depth > 0 m")


#: The study's wall family (docs/study.md, "The task").
WALL_FAMILY = WallFamily()
#: ``--quick``: two holes, one within the arm's reach, one beyond.
QUICK_WALL_FAMILY = WallFamily(holes=(2, 2), near_edge=(0.0, 0.2), far_edge=(1.1, 1.3))

#: Spawn key of the layout's generator (apart from the users' ``[seed, index]``).
LAYOUT_STREAM = 0x1A7
#: Spawn key of a person's motor-noise generator.
NOISE_STREAM = 0x401


def draw_wall_layout(seed: int, family: WallFamily = WALL_FAMILY,
                     handle_height: float | None = None) -> tuple[tuple[float, float], ...]:
    """The layout of study seed ``seed``: holes ``(w, z)`` [m] in the order of visit
    (for :func:`wall_task`).  The same for every user and approach of the seed.
    ``handle_height`` [m]: the start handle's height, given to the hole drawn to be at
    it (clipped to ``family.heights``); None: that hole keeps its drawn height."""
    rng = np.random.default_rng(np.random.SeedSequence(int(seed), spawn_key=(LAYOUT_STREAM,)))
    n = int(rng.integers(family.holes[0], family.holes[1] + 1))
    near = float(rng.uniform(*family.near_edge))
    far = float(rng.uniform(*family.far_edge))
    jitter = rng.uniform(-0.3, 0.3, n)
    z = rng.uniform(*family.heights, n)
    at_handle = int(rng.integers(n))
    order = rng.permutation(n)
    width = (far - near) / n
    w = near + (np.arange(n) + 0.5 + jitter) * width
    if handle_height is not None:
        z[at_handle] = min(max(handle_height, family.heights[0]), family.heights[1])
    return tuple((float(w[i]), float(z[i])) for i in order)


def noise_seed(seed: int, user: int) -> np.random.SeedSequence:
    """The motor-noise seed of user ``user`` of study seed ``seed``: the same in every
    approach (and apart from the stream the user's parameters come from)."""
    return np.random.SeedSequence([int(seed), int(user)], spawn_key=(NOISE_STREAM,))


class Phase(enum.Enum):
    """What the person is doing."""

    REACT = "react"
    REACH = "reach"
    INSERT = "insert"
    DWELL = "dwell"
    EXTRACT = "extract"
    PRESS = "press"  # pressing the mode button: the plan pauses
    HOLD = "hold"  # the end-of-trial hold, after T_f
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
    task keeps the orientation), motor noise included; ``switch_request``
    "locomotion"/"manipulation" or None (the button's press ends now); ``phase``;
    ``done`` once the last insertion is finished (T_f; the hold follows, then the
    phase is DONE); ``noise`` (3,): the unit noise process η at this instant."""

    force: Vec
    switch_request: str | None
    phase: Phase
    done: bool
    noise: Vec | None = None


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
    if not loop and p.hold_time > 0.0:
        segs.append(_Segment(Phase.HOLD, last, duration=p.hold_time))
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


_SeedLike = int | Sequence[int] | np.random.SeedSequence


class SimulatedHuman:
    """The person: plan, hand impedance, effort regulation, motor noise, switching
    policy and the button.

    ``loop=True`` restarts the task after the last hole (for a live demo); then
    ``done`` never becomes true (and there is no end-of-trial hold).  ``finish_time``
    is ``T_f`` [s] once done; ``hold_end`` the end of the hold [s].  ``noise_seed``:
    the person's motor-noise generator (default 0).  ``button``: the handle has a mode
    button (the switch condition); without one the person never presses.  Nothing here
    knows which control approach runs the robot.
    """

    def __init__(self, params: HumanParams, task: Task, loop: bool = False,
                 noise_seed: _SeedLike | None = None, button: bool = True) -> None:
        self.params = params
        self.task = task
        self.loop = loop
        self.button = button
        self.finish_time: float | None = None
        self.hold_end: float | None = None
        self.presses = 0
        self._segs = _plan(task, params, loop)
        self._n_task = len(self._segs) - (1 if self._segs[-1].phase is Phase.HOLD else 0)
        self._policy = SwitchPolicy(params, task.arm_mount_xy)
        self._goals = [np.array(h.approach) for h in task.holes]
        seed = noise_seed if noise_seed is not None else 0
        self._rng = np.random.default_rng(seed)
        self._eta = self._rng.standard_normal(3)  # stationary start
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
        self._press_end = -math.inf  # the plan pauses until then [s]
        self._pending: str | None = None  # the request the press sends when it ends

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
        if t < self._press_end:  # pressing the button: the plan's clock stands still
            self._t_seg += dt
            self._ref_vel = np.zeros(3)
            return
        while self._k < len(self._segs):
            seg = self._segs[self._k]
            if seg.target is None:  # a hold: react, dwell or the end-of-trial hold
                if t - self._t_seg < seg.duration:
                    return
                if seg.phase is Phase.DWELL and self._k == self._n_task - 1 and not self.loop:
                    self.finish_time = self._t_seg + seg.duration
                if seg.phase is Phase.HOLD:
                    self.hold_end = self._t_seg + seg.duration
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
        # the noise process: one draw per call whatever happens, so that it depends on
        # the person and the time only (exact discretisation of a unit-variance OU process)
        a = math.exp(-2.0 * math.pi * p.noise_corner * dt)
        self._eta = a * self._eta + math.sqrt(1.0 - a * a) * self._rng.standard_normal(3)
        self._advance(t, dt, x, xd)
        err = self._ref - x
        force = p.stiffness * (err + self._effort) + p.damping * (self._ref_vel - xd)
        mag = math.sqrt(float(force @ force))
        if mag > p.f_max:
            force *= p.f_max / mag
            mag = p.f_max
        self._rate = min(1.0, max(0.0, (p.f_max - mag) / (p.f_max - p.f_comfort)))
        if p.force_cv > 0.0:  # signal-dependent: SD = cv ||f|| on every axis
            force = force + (p.force_cv * mag) * self._eta
            total = math.sqrt(float(force @ force))
            if total > p.f_max:
                force *= p.f_max / total
        done = self.finish_time is not None
        request = None
        if self._pending is not None and t >= self._press_end:
            request, self._pending = self._pending, None
        if not done and self._k < len(self._segs):
            seg = self._segs[self._k]
            stalled = (seg.target is not None and float(xd @ xd) < p.settle_speed ** 2
                       and float(err @ err) > (3.0 * p.position_tolerance) ** 2)
            wish = self._policy.update(t, seg.hole, self._goals[seg.hole], x,
                                       np.asarray(obs.base, dtype=float), stalled)
            if wish is not None and self.button:
                self.presses += 1
                if p.press_time > 0.0:
                    self._pending, self._press_end = wish, t + p.press_time
                else:
                    request = wish
        phase = Phase.PRESS if t < self._press_end and self.phase is not Phase.DONE else self.phase
        return HumanAction(force, request, phase, done, self._eta.copy())
