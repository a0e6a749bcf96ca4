"""Entity paths, timelines and the default viewer layout (blueprint).

Every entity mmctl logs is named here (the README's "Telemetry" section lists them).
Two timelines index everything: ``cycle`` (sequence: the loop cycle index k) and
``time`` (duration: the cycle's deadline since the loop's origin [s]).

Three rates:

* **full** — one row per published cycle: the inputs of the trial metrics (paper
  eq. 14-16) and the loop timing.  A recording holds every cycle the ring did not drop,
  so metrics recomputed from it equal the daemon's.
* **plot** — every ``round(loop rate / telemetry.plot_rate)``-th cycle.
* **scene** — the 3-D robot, the newest sample at each publisher wake-up
  (``telemetry.scene_rate``).

rerun is imported only inside :func:`blueprint`.
"""

from __future__ import annotations

from typing import Any, Literal, NamedTuple

TIMELINE_CYCLE = "cycle"
TIMELINE_TIME = "time"

Rate = Literal["full", "plot", "scene", "event", "static"]


class Series(NamedTuple):
    """A time-series entity: path, rate, one name per value in a row, unit."""

    path: str
    rate: Rate
    names: tuple[str, ...]
    unit: str


# -- time series: full rate (trial-metric inputs, loop timing) -----------------------
ENERGY = Series("plots/energy", "full", ("E_K", "E_K arm", "E_K base"), "J")
FORCE_NORM = Series("plots/force/norm", "full", ("|f_h|",), "N")
SPEED = Series("plots/speed", "full", ("|v_d|", "|v|"), "m/s")
#: the tool position and FK(q_des) in the mobile base frame (the loop writes world positions;
#: :func:`mmctl.telemetry.batch.base_frame` converts them)
EE_POSITION = Series("plots/ee/position", "full", ("p x", "p y", "p z"), "m")
EE_POSITION_DES = Series("plots/ee/position_des", "full", ("p_des x", "p_des y", "p_des z"), "m")
LOOP_TIMING = Series("plots/loop/timing", "full",
                     ("compute", "slack", "wake latency"), "us")

# -- time series: plot rate ------------------------------------------------------------
FORCE = Series("plots/force/components", "plot",
               ("f_x", "f_y", "f_z", "tau_x", "tau_y", "tau_z"), "N | N m")
ARM_QD = Series("plots/command/arm_qd", "plot",
                tuple(f"qd{i}" for i in range(1, 7)), "rad/s")
BASE_TWIST = Series("plots/command/base_twist", "plot", ("v_x", "v_y", "w_z"), "m/s | rad/s")
WHEELS = Series("plots/command/wheels", "plot", ("FL", "FR", "BL", "BR"), "rad/s")
DROPPED = Series("plots/telemetry/dropped", "plot", ("dropped",), "samples")
#: the scale the limits applied to the IDK's command (1: free); which limit bound it is
#: an event (``limit=...``) when it changes
LIMIT_SCALE = Series("plots/command/limit_scale", "plot", ("limit scale",), "")
#: the robot's two nearest parts' distance (the self-collision check's; its margin is
#: safety.collision_margin, and the binding pair is named by status and the live view)
NEAREST = Series("plots/body/nearest_distance", "plot", ("nearest parts",), "m")

FULL_RATE: tuple[Series, ...] = (ENERGY, FORCE_NORM, SPEED, EE_POSITION, EE_POSITION_DES)
PLOT_RATE: tuple[Series, ...] = (FORCE, ARM_QD, BASE_TWIST, WHEELS, LIMIT_SCALE, NEAREST)
ALL_SERIES: tuple[Series, ...] = FULL_RATE + (LOOP_TIMING,) + PLOT_RATE + (DROPPED,)

# -- 3-D scene (scene rate); world = odometry frame, base = mobile base frame ------------
WORLD = "world"
BASE = "world/base"                    # Transform3D: odometry pose (x, y, yaw)
BASE_FOOTPRINT = "world/base/footprint"  # Boxes3D, static
ARM = "world/base/arm"                 # LineStrips3D through the joint origins (FK)
ARM_JOINTS = "world/base/arm/joints"   # Points3D at the joint origins
HANDLE = "world/base/handle"           # Transform3D: end-effector (handle) frame + axes
TWIST_ARROW = "world/base/v_d"         # Arrows3D: desired linear velocity at the handle
FORCE_ARROW = "world/base/f_h"         # Arrows3D: human force at the handle
P_DES = "world/base/p_des"             # Points3D: preferred position FK(q_des)
BASE_PATH = "world/odometry_path"      # LineStrips3D: recent base positions
#: the robot's URDF (`mmctl model urdf`, its visuals) under this prefix, static, as
#: rerun's URDF loader files it (shapes in the links' named frames, the joints at zero
#: on ``/tf_static``); its root link ``base_link`` hangs on the frame of :data:`BASE`
ROBOT = "world/base/robot"
#: ``ROBOT_JOINTS/root`` (static: BASE's frame -> base_link) and one entity per arm
#: joint, ``ROBOT_JOINTS/<joint name>``: its Transform3D in named frames (parent link ->
#: child link) at every scene frame
ROBOT_JOINTS = "world/base/robot/joints"
#: the arm's six joints' entities, in the arm's joint order
ARM_JOINT_ENTITIES = tuple(f"{ROBOT_JOINTS}/{n}_joint" for n in (
    "shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3"))

#: arrow scales: a drawn arrow is this many metres per [m/s] / per [N]
TWIST_ARROW_SCALE = 1.0
FORCE_ARROW_SCALE = 0.01

# -- events -------------------------------------------------------------------------------
EVENTS = "events"                      # TextLog: mode / safety changes, trial start/stop
TRIAL = "trial"                        # trial/<n>: AnyValues with the bracket and metrics
TRIAL_METRICS = "trial/metrics"        # one row per finished trial (AnyValues + TextLog)

#: keys of a trial-metrics row (SI units) besides the metrics themselves
TRIAL_FIELDS = ("trial", "start_cycle", "stop_cycle", "samples")
METRIC_KEYS = ("E", "F_h", "v", "x_f", "T_f")


def blueprint(history_s: float = 20.0) -> Any:
    """The default viewer layout: 3-D robot + events on the left, plots on the right.

    history_s: the time-series views show the last ``history_s`` seconds [s].
    Returns a ``rerun.blueprint.Blueprint`` (imports rerun).
    """
    import rerun.blueprint as rrb

    window = rrb.VisibleTimeRange(
        TIMELINE_TIME,
        start=rrb.TimeRangeBoundary.cursor_relative(seconds=-history_s),
        end=rrb.TimeRangeBoundary.cursor_relative(),
    )

    def plot(name: str, *paths: str) -> Any:
        contents = [f"/{p}" for p in paths]
        return rrb.TimeSeriesView(name=name, origin="/plots", contents=contents,
                                  time_ranges=window,
                                  plot_legend=rrb.PlotLegend("LeftTop", visible=True))

    camera = rrb.EyeControls3D(position=(-1.7, -1.6, 1.6), look_target=(0.4, 0.0, 0.7),
                               eye_up=(0.0, 0.0, 1.0), tracking_entity=f"/{BASE}")
    left = rrb.Vertical(
        rrb.Spatial3DView(name="Robot (follows the base)", origin=f"/{WORLD}",
                          eye_controls=camera),
        rrb.TextLogView(name="Events", origin=f"/{EVENTS}"),
        row_shares=[3, 1],
    )
    right = rrb.Vertical(
        plot("Human force |f_h| and components [N]", FORCE_NORM.path, FORCE.path),
        plot("End-effector speed: desired / actual [m/s]", SPEED.path),
        plot("Kinetic energy E_K: total / arm / base [J]", ENERGY.path),
        rrb.Tabs(
            plot("Arm joint velocity commands [rad/s]", ARM_QD.path),
            plot("Base twist command [m/s, rad/s]", BASE_TWIST.path),
            plot("Wheel speed commands [rad/s]", WHEELS.path),
            plot("Limits: scale of the command (1: free; events name the limit)",
                 LIMIT_SCALE.path),
            plot("Self-collision: the robot's two nearest parts' distance [m]",
                 NEAREST.path),
            plot("End-effector position p vs p_des [m]", EE_POSITION.path,
                 EE_POSITION_DES.path),
        ),
        plot("Loop timing [us]", LOOP_TIMING.path, DROPPED.path),
    )
    return rrb.Blueprint(
        rrb.Horizontal(left, right, column_shares=[2, 3]),
        rrb.TimePanel(timeline=TIMELINE_TIME, state="collapsed", play_state="following"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
    )
