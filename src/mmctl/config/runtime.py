"""`loop:`, `safety:`, `daemon:`, `telemetry:` and `sim:` — the runtime around the control chain."""

from __future__ import annotations

import re
from typing import Literal

from mmctl.config.schema import param, section
from mmctl.errors import ConfigError

#: The largest miss budget: one that never runs out (`mmctl bench loop` measures misses).
MAX_MISS_BUDGET = 1_000_000_000


@section
class LoopConfig:
    """The fixed-period control loop."""

    rate_hz: float = param(
        500.0, unit="Hz", ge=1.0, le=1000.0,
        why="the UR10e's RTDE runs at 500 Hz; above 1 kHz the period is shorter than a "
        "CAN sensor's request and reply; below 1 Hz there is no control")
    spin_margin: float = param(
        0.0001, unit="s", ge=0.0, le=0.01,
        why="a busy-wait window inside one period (checked against loop.rate_hz)",
        doc="sleep until this long before the deadline, then spin (holding the interpreter: "
        "100 us keeps wake latency p99 ~15 us with a 1 us timer slack; 300 us measured "
        "compute p99 15 % worse, the other threads' work pushed into the cycle)",
    )
    max_consecutive_misses: int = param(
        5, ge=1, le=MAX_MISS_BUDGET, doc="consecutive deadline misses -> fault",
        why="a count, not a time (one miss may be a long stall, which the devices' "
        "watchdogs catch): from every miss a fault to 1e9, a budget that never runs out "
        "(benchmarks that measure the misses)")
    max_total_misses: int = param(
        1000, ge=1, le=MAX_MISS_BUDGET, doc="total misses since enable -> fault",
        why="a count: from every miss a fault to 1e9 (23 days of every cycle late at "
        "500 Hz), a budget that never runs out")
    rt_priority: int = param(0, ge=0, le=99, doc="SCHED_FIFO priority; 0 = do not ask",
                             why="SCHED_FIFO priorities are 1..99")
    cpu_affinity: tuple[int, ...] = param(
        (), ge=0, le=1023, doc="CPUs to pin the loop thread to; () = any",
        why="CPU numbers of a cpu_set_t (1024 CPUs)")
    cpu_dma_latency: int = param(
        -1, unit="us", ge=-1, le=2_000_000,
        why="the kernel's PM QoS range (at most 2 s)",
        doc="PM QoS request held while the daemon runs (/dev/cpu_dma_latency): CPUs idle "
        "only in states that wake within this time; 0 = never halt (poll); -1 = do not ask",
    )
    switch_interval: float = param(
        0.0001, unit="s", ge=1e-6, le=0.1,
        doc="Python GIL switch interval of the daemon: how long another thread may keep "
        "the loop thread waiting for the interpreter",
        why="from a microsecond to 50 periods at 500 Hz",
    )
    gc_in_slack: bool = param(
        True,
        doc="keep Python's garbage collector out of the cycle: automatic collection off "
        "while the loop runs, the young generation collected in a cycle's slack every "
        "gc_every cycles, the older ones every second and minute, each only when at "
        "least gc_margin is left before the next deadline (start-up objects are frozen "
        "out of every collection either way)",
        why="an automatic collection runs in whichever allocation crosses its threshold, "
        "the loop's included")
    gc_every: int = param(
        50, ge=1, le=100_000,
        doc="with gc_in_slack: cycles between two collections of the young generation",
        why="10 Hz at 500 Hz; the young generation then holds a few thousand objects")
    gc_margin: float = param(
        0.0008, unit="s", ge=0.0, le=0.1,
        doc="with gc_in_slack: the least time left before the next deadline for a "
        "collection to run in this cycle's slack (else the next cycle's)",
        why="a young-generation collection takes tens of microseconds, a full one up to "
        "a few hundred")
    timing_samples: int = param(
        8192, ge=2, le=1_048_576, doc="cycles kept in the timing ring",
        why="2^20 cycles is 35 min at 500 Hz, ~25 MB of ring")
    sensor_request: Literal["start", "end"] = param(
        "start",
        doc="when a request/reply sensor (CAN) is asked for its next sample: at the end of "
        "the cycle (the answer arrives in the idle time; the sample is a period old when "
        "used) or at its start (the arm and the base are read while it answers: a fresher "
        "sample, and the reply's wait inside the cycle); `mmctl bench loop` measures both")
    base_divider: int = param(
        2, ge=1, le=50, why="at 500 Hz: every cycle down to 10 Hz",
        doc="send the base twist every n-th cycle (each command is 4 RPDOs + SYNC + 4 "
        "TPDOs: ~50 % of a 1 Mbit/s CAN bus at 500 Hz); stop commands go out at once",
    )
    base_jump: float = param(
        0.001, unit="m/s | rad/s", ge=1e-6, le=1.0,
        why="from a micrometre per second to most of the base's 1.5 m/s",
        doc="a base twist differing from the last one sent by more than this goes out in "
        "its own cycle, whatever base_divider says (a new push reaches the wheels one "
        "period sooner; steady motion keeps the divided rate)")


    def validate(self, path: str, source: str | None) -> None:
        period = 1.0 / self.rate_hz
        if self.spin_margin >= period:
            raise ConfigError(f"{path}.spin_margin" if path else "spin_margin", self.spin_margin,
                              f"must be < the loop period 1 / loop.rate_hz = {period:g} s",
                              source)


@section
class SafetyConfig:
    """Fault thresholds not owned by a device section."""

    max_condition: float = param(
        1e4, gt=1.0, le=1e8,
        doc="condition number of the whole-body J J^T above which the pose is 'singular'",
        why="a condition number is > 1; past 1e8 the inverse of J J^T has lost half the "
        "digits of a double before the check trips",
    )
    brake_condition: float = param(
        0.05, gt=0.0, le=1.0,
        doc="singularity braking: a command toward a singular pose is braked to rest at "
        "the condition number brake_condition x max_condition (0.05: 500, where "
        "sigma_min / sigma_max is 4.5x the fault's; near the wrist singularity wrist 2 "
        "rests 6-8 deg from it), so hand guiding never pushes the arm into the singular "
        "fault; moving away is free; 1: the braking ends at the fault's own level",
        why="a fraction of safety.max_condition")
    collision_check: bool = param(
        True, doc="self-collision avoidance: brake a command that brings two parts of the "
        "robot nearer than collision_margin (docs/hand-guiding.md, the robot's body)")
    collision_margin: float = param(
        0.05, unit="m", ge=0.005, le=0.3,
        doc="a command closing two of the robot's parts is braked to rest this far apart "
        "(the parts' shapes are robot.link_radii and the rest); moving apart is free",
        why="from 5 mm to 30 cm (50 is millimetres)")
    collision_tolerance: float = param(
        0.02, unit="m", ge=0.001, le=0.2,
        doc="a pair nearer than collision_margin - collision_tolerance is the "
        "self_collision fault, and enabling is refused while it lasts",
        why="from a millimetre to 20 cm inside the margin")


@section
class DaemonConfig:
    """Control socket and process settings."""

    socket_path: str = param(
        "", doc="control socket; '' = $RUNTIME_DIRECTORY or $XDG_RUNTIME_DIR or /tmp, + mmctl.sock"
    )
    socket_mode: int = param(0o660, ge=0, le=0o777, why="file permission bits (0o777 at most)")
    ready_timeout: float = param(
        10.0, unit="s", ge=0.1, le=600.0,
        doc="READY=1 is sent after the first healthy cycle, or after this long regardless",
        why="the devices connect in seconds; 10 min is past any service manager's patience",
    )
    command_timeout: float = param(
        5.0, unit="s", ge=0.1, le=300.0,
        doc="how long a control command waits for the loop to take it",
        why="enable/disable take up to the drives' stop time plus a few SDO timeouts; an "
        "operator waits minutes at most",
    )
    switch_input: int = param(
        -1, ge=-1, le=17, why="the UR's digital inputs are 0..17; -1 = none",
        doc="UR digital input (0-7 standard, 8-15 configurable, 16-17 tool) of the handle "
        "button that toggles manipulation/locomotion in switch mode; -1 = no button",
    )
    log_level: Literal["debug", "info", "warning", "error"] = param("info")


@section
class EnablingConfig:
    """The enabling (hold-to-run) switch on the handle, read from the UR's digital inputs
    through RTDE in every cycle.  Motion only while it is held: released, the armed
    robot decelerates to rest on the joint and base acceleration limits and stays armed
    but still until it is held again.  Two contacts (a dual-channel three-position
    switch) must agree: disagreeing longer than ``discrepancy_time`` (a broken wire, a
    welded contact) is the fault ``enabling_device_fault``; an input the arm cannot
    report (its link down) is the arm's fault."""

    inputs: tuple[int, ...] = param(
        (), ge=0, le=17,
        doc="UR digital inputs (0-7 standard, 8-15 configurable, 16-17 tool) of the "
        "switch's contacts: one, or two for a dual-channel switch; () = no enabling "
        "switch (the robot moves whenever armed)",
        why="the UR's digital inputs are 0..17")
    active_low: bool = param(
        False, doc="the contacts read 0 while the switch is held (and 1 released)")
    discrepancy_time: float = param(
        0.05, unit="s", ge=0.002, le=1.0,
        doc="how long two contacts may disagree (one switching before the other) "
        "before it is a fault",
        why="contacts of one switch settle within milliseconds; a second is a broken "
        "channel that has already been trusted too long")

    def validate(self, path: str, source: str | None) -> None:
        key = f"{path}.inputs" if path else "inputs"
        if len(self.inputs) > 2:
            raise ConfigError(key, list(self.inputs),
                              "must list at most 2 inputs (one per contact of the switch)",
                              source)
        if len(set(self.inputs)) != len(self.inputs):
            raise ConfigError(key, list(self.inputs),
                              "must be two different inputs (one per contact)", source)


@section
class TelemetryConfig:
    """rerun telemetry (off by default; `mmctl run --viewer/--connect/--record` turn it on)."""

    enabled: bool = param(False, doc="publish; with no destination below: the loopback viewer")
    plot_rate: float = param(
        100.0, unit="Hz", ge=0.1, le=1000.0, doc="rate of the plot-only series",
        why="at most one point per cycle of the fastest loop (1 kHz)")
    scene_rate: float = param(
        15.0, unit="Hz", ge=0.1, le=200.0,
        why="a viewer draws at most ~200 frames/s; below 0.1 Hz it is no live view",
        doc="3-D frames and publisher wake-ups per second (fewer wake-ups, larger batches: "
        "less interference with the loop; `mmctl bench loop --telemetry` measures it)",
    )
    queue_size: int = param(
        4096, ge=16, le=1_048_576, doc="samples (ring rows) held between the loop and the publisher",
        why="at least a few cycles; 2^20 rows is 35 min at 500 Hz in shared memory")
    process: bool = param(
        True, doc="run the publisher (batching, 3-D frames, rerun) in a child process that "
        "maps the loop's sample ring from shared memory, so none of its work takes the "
        "daemon's interpreter lock; false: a thread of the daemon, paced into the loop's "
        "idle time (`mmctl bench loop --telemetry` compares them)")
    viewer: bool = param(False, doc="spawn a local rerun viewer (127.0.0.1:9876)")
    connect: str = param(
        "", doc="stream to a running viewer: HOST:PORT, PORT or rerun+http URL; '' = no"
    )
    record: str = param("", doc="save a recording to this .rrd file; '' = no")


@section
class Ros2Config:
    """The ROS 2 bridge (the `mmctl[ros2]` extra; off by default): joint states, TF,
    wrenches, diagnostics and the robot description on DDS, for RViz, `ros2 bag` and a
    lab's other nodes.  Read-only: it subscribes to nothing, so it never commands or arms
    the robot."""

    enabled: bool = param(False, doc="run the bridge (a child process, off the loop's CPUs)")
    domain_id: int = param(0, ge=0, le=232, doc="the ROS_DOMAIN_ID the bridge joins",
                           why="ROS 2's domain ids, 0-232 (DDS ports beyond are invalid)")
    topic_prefix: str = param(
        "", doc="a namespace before every topic ('' = none: /joint_states, /tf, ...; "
        "'robot1': /robot1/joint_states, ...)")
    rate: float = param(100.0, unit="Hz", ge=1.0, le=500.0,
                        doc="joint states, TF, wrenches and the desired twist",
                        why="at most the loop's rate; below 1 Hz RViz shows no motion")
    diagnostics_rate: float = param(1.0, unit="Hz", ge=0.1, le=10.0,
                                    doc="/diagnostics, as ros2_control's own",
                                    why="a diagnostic aggregator expects about 1 Hz")

    def validate(self, path: str, source: str | None) -> None:
        key = f"{path}.topic_prefix" if path else "topic_prefix"
        words = [w for w in self.topic_prefix.strip("/").split("/") if w]
        if any(not re.fullmatch(r"[A-Za-z][A-Za-z0-9_]*", w) for w in words):
            raise ConfigError(key, self.topic_prefix,
                              "must be a ROS 2 namespace: words of letters, digits and _ "
                              "(each starting with a letter), separated by /", source)
    discovery_range: Literal["localhost", "subnet"] = param(
        "localhost", doc="who discovers the bridge: this machine only (DDS on the "
        "loopback interface), or the lab's subnet (ROS_AUTOMATIC_DISCOVERY_RANGE)")


@section
class SimConfig:
    """The simulated robot (`mmctl sim`, its own process) that `mmctl run` drives when
    no hardware is configured."""

    enabled: bool = param(
        False, doc="this configuration drives the simulated robot: `mmctl run` attaches to "
        "the `mmctl sim` answering on sim.socket_path, or starts one as its child")
    human: bool = param(False, doc="a simulated person pushes the handle")
    auto_enable: bool = param(
        False, doc="arm the simulated robot after start-up (ignored unless sim.enabled)"
    )
    human_seed: int = param(0, ge=0, le=2**32 - 1, doc="which simulated person (seeded parameters)",
                            why="numpy seeds are 32-bit")
    host: str = param(
        "127.0.0.2", min_len=1,
        doc="loopback address the simulated robot serves CAN on (socketcand); the CAN "
        "sections on 'socketcand' name it as their host")
    can_port: int = param(29536, ge=1, le=65535, doc="its socketcand port (socketcand's default)",
                          why="a TCP port")
    socket_path: str = param(
        "", doc="the simulation's control socket (`mmctl sim status|push|fault|person`); "
        "'' = next to the daemon's: $RUNTIME_DIRECTORY, $XDG_RUNTIME_DIR or /tmp/mmctl-$UID, "
        "+ mmctl-sim.sock")
    ready_timeout: float = param(
        60.0, unit="s", ge=1.0, le=600.0,
        doc="how long `mmctl run` waits for the `mmctl sim` it started, and then for "
        "its auto-enable (tare, enable)",
        why="it starts in seconds (a minute on a loaded machine); 10 min is a hang")
    handle_mass: float | None = param(
        None, unit="kg", ge=0.0, le=12.5,
        doc="the simulated handle's true mass, which the simulated sensor weighs (what "
        "`mmctl calibrate tool` should find); null: sensor.wrench.handle_mass (the "
        "daemon's model is exact)",
        why="the UR10e's payload is 12.5 kg (600 is grams)")
    handle_com: tuple[float, ...] | None = param(
        None, unit="m", shape=(3,), ge=-0.5, le=0.5,
        doc="the simulated handle's true centre of mass in the sensor frame; null: "
        "sensor.wrench.handle_com",
        why="a handle within 0.5 m of the sensor (80 is millimetres)")
    sensor_bias: tuple[float, ...] = param(
        (1.2, -0.7, 2.5, 0.04, -0.03, 0.02), unit="N | N m", shape=(6,),
        ge=(-100.0,) * 3 + (-5.0,) * 3, le=(100.0,) * 3 + (5.0,) * 3,
        doc="the simulated sensor's constant offset fx, fy, fz [N], tx, ty, tz [N m] (what "
        "a tare or `mmctl calibrate tool` removes)",
        why="an offset well inside the Axia80 M20's +-500 N and +-20 N m (mN are caught)")
    # The simulated base's departure from its commands (sim/wheels.py BaseDynamics; the
    # fakes' drives and the study's plant alike).  Sources and arguments: docs/study.md,
    # "The base plant".  0 / 0 / 0 / 0 is the ideal base of before issue 19.
    base_latency: float = param(
        0.002, unit="s", ge=0.0, le=0.1,
        doc="dead time from a wheel velocity command to the drive acting on it. 2 ms: the "
        "daemon sends the targets at the end of its cycle (0.3-0.6 ms of compute), 4 RPDOs + "
        "SYNC take ~0.4 ms on a 1 Mbit/s CAN bus (5 frames of 50-90 bits, CiA 301), and a "
        "CiA 402 drive applies the SYNC-latched target at its next profile cycle (<= 1 ms "
        "at the 1 kHz interpolation cycle: the cyclic modes' 1 ms time base, 60C2h = -3, "
        "Nanotec PD4-C CANopen manual; Elmo servo drives: 2.75 kHz position loop)",
        why="from none to 50 control periods (a bus that late is broken)")
    base_velocity_tau: float = param(
        0.01, unit="s", ge=0.0, le=0.5,
        doc="time constant of the drives' velocity loop (wheel speed behind the drive's "
        "ramped demand, first order). 10 ms = a 16 Hz loop: servo drives reach a few "
        "hundred Hz at an unloaded shaft (Elmo: velocity loop < 350 Hz), but a wheel drive "
        "carrying a quarter of a ~150 kg base through a gearbox and elastomer rollers is "
        "tuned below the drivetrain's first resonance, of order 25 Hz "
        "(sqrt(1e6 N/m / 37 kg) / 2 pi); 0 = the wheels follow the demand exactly",
        why="from none to a loop so slow (0.3 Hz) no base would be driven with it")
    base_slip_longitudinal: float = param(
        0.01, ge=0.0, le=0.5,
        doc="fraction of the wheels' odometry the base does not achieve along its x axis "
        "(mecanum roller slip; the encoders do not see it, the world does). 1 %: the "
        "elastomer rollers' compression under a quarter of ~150 kg (~0.5 mm of a 127 mm "
        "radius, 0.4 %) plus rolling-contact creep at the small traction of hand-guided "
        "motion (Carter: (a / 2R) F/N ~ 0.3 % for a 6 mm contact, F/N ~ 0.1), rounded up",
        why="from none to half the motion lost (a base on ice)")
    base_slip_lateral: float = param(
        0.03, ge=0.0, le=0.5,
        doc="as sim.base_slip_longitudinal along the base's y axis (sideways). 3 %: "
        "sideways, each wheel pushes along its 45-degree roller axes (sqrt 2 more force "
        "per newton moved) and the spinning rollers add their bearing and rolling drag, so "
        "the creep term grows about threefold; mecanum bases are known to strafe short of "
        "their odometry (gm0 drivetrain guide; far more on carpet than on a hard floor). "
        "A multibody simulation of a mecanum platform loses 0.19 % forward and 1.42 % "
        "sideways (Li et al. 2018, J. Robotics, doi:10.1155/2018/9373580, Table 2): the "
        "same order, sideways several times forward",
        why="from none to half the motion lost (a base on ice)")

    def validate(self, path: str, source: str | None) -> None:
        import ipaddress

        try:
            loopback = ipaddress.ip_address(self.host).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ConfigError(f"{path}.host" if path else "host", self.host,
                              "must be a loopback address (127.0.0.0/8 or ::1): the "
                              "simulated robot never serves beyond this machine", source)
