"""`admittance:`, `idk:` and `limits:` — the control chain's parameters."""

from __future__ import annotations

import math
from enum import Enum
from typing import Literal, get_args

from mmctl.config.schema import param, section, sub
from mmctl.errors import ConfigError


class Mode(str, Enum):
    """The IDK strategy selected by the operator (``idk.strategy``, `mmctl mode`): the one
    list of mode names (the config's choices, the controller's, the telemetry codes)."""

    MIN_ENERGY = "min-energy"
    LOCOMOTION = "locomotion"
    SWITCH = "switch"
    MANIPULATION = "manipulation"
    CONSTRAINED = "constrained-min-energy"


class SwitchMode(str, Enum):
    """Sub-mode of the switch benchmark (``idk.switch.initial``, `mmctl switch`)."""

    MANIPULATION = "manipulation"
    LOCOMOTION = "locomotion"


#: the names of :class:`Mode`, in its order
STRATEGIES: tuple[str, ...] = tuple(m.value for m in Mode)
#: the config schema's type of a mode name (a Literal: the schema checks the choices)
Strategy = Literal["min-energy", "locomotion", "switch", "manipulation", "constrained-min-energy"]
if get_args(Strategy) != STRATEGIES:  # pragma: no cover -- a edit that forgot one of them
    raise AssertionError(f"config.control.Strategy {get_args(Strategy)} != Mode {STRATEGIES}")


@section
class AdmittanceConfig:
    """Virtual admittance M v' + B v = f_h, per axis (vx, vy, vz, wx, wy, wz)."""

    mass: tuple[float, ...] = param(
        (4.0,) * 6, unit="kg | kg m^2", shape=(6,), ge=0.1, le=1000.0,
        doc="diagonal of the virtual mass M (must be positive definite: every entry > 0)",
        why="positive definite; the paper's 4; a virtual ton is beyond a person's push",
    )
    damping: tuple[float, ...] = param(
        (75.0,) * 6, unit="N s/m | N m s/rad", shape=(6,), ge=1.0, le=10_000.0,
        doc="diagonal of the virtual damping B (every entry > 0)",
        why="the paper's 75; below 1 a 15 N push asks for 15 m/s, above 10 000 for 1.5 mm/s",
    )


@section
class LocomotionConfig:
    """Weights of the damped weighted least squares of the locomotion benchmark (eq. 7).

    Not published in the paper.  Our defaults: the task weight W_alpha is large so the
    twist is tracked closely; W_beta penalises arm joint speed 1000x more than base
    speed, so the base carries the motion and the arm stays near q_des.  Checked
    (tests/test_idk.py, tests/test_step.py): for horizontal 0.2 m/s pushes near q_des the
    base makes 99.99 % of the end-effector velocity (arm joints ~1e-4 rad/s), and a
    steady 15.8 N push for 2 s leaves the arm within 1e-3 rad of q_des; the twist
    error from the damping is < 1 %.
    """

    w_alpha: tuple[float, ...] = param(
        (1.0e3,) * 6, shape=(6,), ge=1e-6, le=1e9, doc="task weights",
        why="relative weights: beyond 1e9 the normal equations lose the precision of doubles")
    w_beta: tuple[float, ...] = param(
        (1.0,) * 6 + (1.0e-3,) * 3, shape=(9,), ge=0.0, le=1e9,
        doc="velocity penalties (6 arm joints, then base vx, vy, wz)",
        why="relative weights: beyond 1e9 the normal equations lose the precision of doubles",
    )


@section
class SwitchConfig:
    """The switch benchmark: manipulation (arm only) <-> locomotion, blended."""

    initial: Literal["manipulation", "locomotion"] = param("manipulation")  # SwitchMode
    blend_time: float = param(
        0.3, unit="s", gt=0.0, le=5.0, doc="cross-fade time of a toggle",
        why="one cycle (a step) up to a 5 s fade that a person would feel as a lag")


@section
class ConstrainedConfig:
    """Constrained min-energy QP (hard joint position/velocity/acceleration limits)."""

    max_iter: int = param(200, ge=1, le=100_000, doc="QP solver iteration cap per cycle",
                          why="one ADMM iteration takes microseconds: 100 000 would fill "
                          "many 2 ms cycles")
    eps: float = param(1e-6, ge=1e-12, le=1e-2, doc="QP solver tolerance",
                       why="below 1e-12 is below double precision of the QP; above 1 % the "
                       "constraints are not held")
    task_weight: float = param(
        1e6, ge=1.0, le=1e12,
        why="the soft task must outweigh the energy term (>= 1); beyond 1e12 the QP is "
        "ill-conditioned in doubles",
        doc="weight rho of the soft task |J qd - v_d|^2 rho / 2 used when a bound is active "
        "(keeps the QP feasible; the twist error is ~ |M (qd - qd_null)| / rho)",
    )


@section
class IdkConfig:
    """Inverse differential kinematics."""

    strategy: Strategy = param("min-energy", doc="IDK strategy at start-up")
    null_gain: tuple[float, ...] = param(
        (1.0,) * 6 + (0.0,) * 3, unit="1/s", shape=(9,), ge=0.0, le=100.0,
        doc="diagonal of G in (I - J#J) G (q_des - q); base entries are 0 in the paper",
        why="the paper's 1; at 100/s a 2 ms cycle already pulls 20 % of the way to q_des",
    )
    singular_threshold: float = param(
        1e-3, ge=1e-9, le=1.0,
        doc="smallest eigenvalue of J M^-1 J^T (or J J^T) below which damping starts",
        why="below 1e-9 damping starts only once the inverse has lost its digits; above 1 "
        "every pose is damped",
    )
    max_damping: float = param(
        1e-2, ge=1e-9, le=1.0, doc="damping added at an exactly singular configuration",
        why="must be > 0 to invert a singular matrix; above 1 it swamps the task",
    )
    avoid_joint_limits: bool = param(
        True,
        doc="min-energy and locomotion hand the motion of an arm joint that nears its "
        "position limit to the other joints and the base (the joint is held to a braking "
        "curve 4x gentler than the limits' own), so the end-effector keeps following; "
        "false: the limits scale the whole command and the end-effector stops with it")
    locomotion: LocomotionConfig = sub(LocomotionConfig)
    switch: SwitchConfig = sub(SwitchConfig)
    constrained: ConstrainedConfig = sub(ConstrainedConfig)


_DEG = 3.141592653589793 / 180.0
#: ISO/TS 15066 body regions where transient contact is permitted (mmctl.control.iso15066)
BodyRegionName = Literal["none", "neck", "back", "chest", "abdomen", "pelvis", "upper_arm",
                         "lower_arm", "hand", "thigh", "lower_leg"]
_TWO_PI = 6.2832  # [rad] 2 pi, rounded up: the UR10e's +-360 deg joint range

#: the UR10e's joint speed limits [rad/s] (120 deg/s base and shoulder, 180 deg/s the
#: others), to 4 decimals (rounded up: the defaults are the exact values)
UR10E_JOINT_SPEED = (2.0944, 2.0944, 3.1416, 3.1416, 3.1416, 3.1416)


@section
class LimitsConfig:
    """Velocity/acceleration/position limits; q' is scaled as a whole to respect them.

    Upper bounds are the hardware's own limits (SPEC section 2: the UR10e's tables, the
    RB-KAIROS+ vendor configuration): a configured limit may only be tighter."""

    joint_velocity: tuple[float, ...] = param(
        (120 * _DEG, 120 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG, 180 * _DEG),
        unit="rad/s", shape=(6,), ge=0.01, le=UR10E_JOINT_SPEED, doc="UR10e joint speed limits",
        why="the UR10e's own limits: 120 deg/s (base, shoulder), 180 deg/s (the others)",
    )
    joint_acceleration: tuple[float, ...] = param(
        (4.0,) * 6, unit="rad/s^2", shape=(6,), ge=0.1, le=40.0,
        doc="arm joint acceleration limits",
        why="ur_rtde's ceiling on a joint acceleration is 40 rad/s^2",
    )
    joint_position_min: tuple[float, ...] = param(
        (-2 * 3.141592653589793, -2 * 3.141592653589793, -3.141592653589793,
         -2 * 3.141592653589793, -2 * 3.141592653589793, -2 * 3.141592653589793),
        unit="rad", shape=(6,), ge=-_TWO_PI, le=_TWO_PI,
        why="the UR10e's joints turn +-360 deg",
    )
    joint_position_max: tuple[float, ...] = param(
        (2 * 3.141592653589793, 2 * 3.141592653589793, 3.141592653589793,
         2 * 3.141592653589793, 2 * 3.141592653589793, 2 * 3.141592653589793),
        unit="rad", shape=(6,), ge=-_TWO_PI, le=_TWO_PI,
        why="the UR10e's joints turn +-360 deg",
    )
    position_margin: float = param(
        0.15, unit="rad", ge=0.001, le=1.0,
        doc="how far inside a joint position limit the position braking brings a joint "
        "to rest (it brakes on 80 % of the acceleration limits from wherever that takes)",
        why="from a milliradian to ~57 deg (a margin in degrees, e.g. 10, is caught)"
    )
    base_linear_velocity: float = param(
        1.5, unit="m/s", ge=0.01, le=1.5,
        why="the RB-KAIROS+ vendor configuration's 1.5 m/s")
    base_angular_velocity: float = param(
        3.0, unit="rad/s", ge=0.01, le=3.0,
        why="the RB-KAIROS+ vendor configuration's 3 rad/s")
    base_linear_acceleration: float = param(
        3.0, unit="m/s^2", ge=0.05, le=3.0,
        why="the RB-KAIROS+ vendor configuration's 3 m/s^2")
    base_angular_acceleration: float = param(
        3.0, unit="rad/s^2", ge=0.05, le=6.0,
        why="the vendor's 3 m/s^2 of the wheels, turning in place: 3 / (0.215 + 0.269) m "
        "= 6.2 rad/s^2")
    wheel_velocity: float = param(
        27.27, unit="rad/s", ge=0.1, le=27.27,
        why="the RB-KAIROS+ vendor configuration's 27.27 rad/s")
    ee_linear_velocity: float = param(
        1.0, unit="m/s", ge=0.01, le=3.0, doc="end-effector speed cap",
        why="ur_rtde's ceiling on a tool speed is 3 m/s")
    ee_angular_velocity: float = param(
        1.5, unit="rad/s", ge=0.01, le=6.0,
        why="the wrist's 180 deg/s plus the base's 3 rad/s is 6.1 rad/s")
    body_region: BodyRegionName = param(
        "chest",
        doc="ISO/TS 15066 body region whose transient-contact values set the whole-body "
        "caps below when they are not given (mmctl.control.iso15066, docs/hand-guiding.md: "
        "chest: 1.57 J, base 0.32 m/s, end-effector 0.53 m/s); none: no such caps")
    energy: float | None = param(
        None, unit="J", gt=0.0, le=100.0,
        doc="cap on the whole-body kinetic energy E_K of the command (the paper's "
        "block-diagonal M); null: F_T^2 / (2 k) of body_region",
        why="ISO/TS 15066's largest transient energy is 2.6 J (pelvis); 100 J is a "
        "115 kg base at 1.3 m/s")
    base_speed: float | None = param(
        None, unit="m/s", gt=0.0, le=1.5,
        doc="cap on the base's linear speed (besides base_linear_velocity); null: "
        "F_T / sqrt(mu k) of body_region with the whole robot's mass",
        why="the RB-KAIROS+ vendor configuration's 1.5 m/s")
    ee_speed: float | None = param(
        None, unit="m/s", gt=0.0, le=3.0,
        doc="cap on the end-effector's linear speed (besides ee_linear_velocity); null: "
        "F_T / sqrt(mu k) of body_region with the arm's effective mass M/2 + m_L",
        why="ur_rtde's ceiling on a tool speed is 3 m/s")
    profile: Literal["normal", "reduced"] = param(
        "normal", doc="the limits' profile at start-up (mmctl profile switches at run time): "
        "reduced caps the end-effector at reduced_ee_speed, for first runs")
    reduced_ee_speed: float = param(
        0.25, unit="m/s", gt=0.0, le=0.25,
        doc="the end-effector speed cap of the reduced profile",
        why="ISO 10218-1's reduced speed for hand guiding is 0.25 m/s at most")

    def validate(self, path: str, source: str | None) -> None:
        for i, (lo, hi) in enumerate(zip(self.joint_position_min, self.joint_position_max)):
            if not lo < hi:
                raise ConfigError(
                    f"{path}.joint_position_min[{i}]", lo,
                    f"must be < joint_position_max[{i}] = {hi}", source,
                )


def _convex_area(points: tuple[tuple[float, ...], ...]) -> float | None:
    """The signed area of a simple convex polygon (> 0 counter-clockwise), or None
    when it is not strictly convex (a reflex or straight corner, a crossing)."""
    n = len(points)
    turns = []
    for i in range(n):
        (ax, ay), (bx, by), (cx, cy) = points[i], points[(i + 1) % n], points[(i + 2) % n]
        turns.append((bx - ax) * (cy - by) - (by - ay) * (cx - bx))
    if not (all(t > 0.0 for t in turns) or all(t < 0.0 for t in turns)):
        return None
    area = 0.5 * sum(points[i][0] * points[(i + 1) % n][1] - points[(i + 1) % n][0] * points[i][1]
                     for i in range(n))
    # a star (pentagram) turns one way at every corner but winds twice: its turns sum
    # to more than 2 pi; a convex polygon's exterior angles sum to exactly 2 pi
    total = 0.0
    for i in range(n):
        (ax, ay), (bx, by), (cx, cy) = points[i], points[(i + 1) % n], points[(i + 2) % n]
        a1, a2 = math.atan2(by - ay, bx - ax), math.atan2(cy - by, cx - bx)
        total += (a2 - a1 + math.pi) % (2.0 * math.pi) - math.pi
    return area if abs(abs(total) - 2.0 * math.pi) < 1e-6 else None


@section
class WallsConfig:
    """Virtual walls: an end-effector box (base frame) and a base keep-in area (world
    frame, from odometry).  Near a wall the speed into it is bounded by a braking curve
    that falls to zero at the wall; along and away from it motion stays free
    (docs/hand-guiding.md, :mod:`mmctl.control.walls`)."""

    ee_box: tuple[tuple[float, ...], ...] | None = param(
        None, unit="m", shape=(2, 3), ge=-2.0, le=2.0,
        doc="[[x_min, y_min, z_min], [x_max, y_max, z_max]] the handle's (tool point's) "
        "box in the base frame (e.g. z_min keeps it off the base's deck and the floor); "
        "null: none",
        why="the UR10e reaches 1.3 m from its base (values in millimetres are caught)")
    base_area: tuple[tuple[float, ...], ...] = param(
        (), unit="m", shape=(None, 2), min_len=3, ge=-1000.0, le=1000.0,
        doc="[[x, y], ...] the corners of a convex area in the world frame (odometry's: "
        "the base starts at the origin heading +x) the base's centre stays in; []: none",
        why="a lab's floor within a kilometre of the start")
    margin: float = param(
        0.15, unit="m", gt=0.0, le=2.0,
        doc="the distance from a wall at which the speed into it may still be the speed "
        "cap; the approach curve (a braking at 80 % of the acceleration limits) falls "
        "to 0 at the wall, and starts farther out when this is shorter than the braking "
        "distance from the cap",
        why="centimetres brake hard; beyond 2 m the wall is felt across a room")

    def validate(self, path: str, source: str | None) -> None:
        box = self.ee_box
        if box is not None and not all(lo < hi for lo, hi in zip(box[0], box[1])):
            raise ConfigError(f"{path}.ee_box", [list(r) for r in box],
                              "each minimum (first row) must be below its maximum "
                              "(second row)", source)
        area = self.base_area
        if area:
            signed = _convex_area(area)
            if signed is None:
                raise ConfigError(f"{path}.base_area", [list(r) for r in area],
                                  "must be the corners of a convex polygon, each once, in "
                                  "order", source)
            inside = all(
                (bx - ax) * (0.0 - ay) - (by - ay) * (0.0 - ax) > 0.0 if signed > 0.0
                else (bx - ax) * (0.0 - ay) - (by - ay) * (0.0 - ax) < 0.0
                for (ax, ay), (bx, by) in zip(area, area[1:] + area[:1]))
            if not inside:
                raise ConfigError(f"{path}.base_area", [list(r) for r in area],
                                  "must contain the origin: odometry starts there, where "
                                  "the daemon starts", source)
            if abs(signed) < 1.0:
                raise ConfigError(f"{path}.base_area", [list(r) for r in area],
                                  f"encloses {abs(signed):.3g} m^2; the base needs at "
                                  "least 1 m^2", source)
