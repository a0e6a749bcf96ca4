"""`arm:` — the UR10e link (ur_rtde)."""

from __future__ import annotations

from mmctl.config.schema import param, section

#: ur_rtde's own ceiling on a joint acceleration (UR_JOINT_ACCELERATION_MAX) [rad/s^2]
UR_JOINT_ACCELERATION_MAX = 40.0


@section
class ArmConfig:
    """UR10e connection and command parameters."""

    host: str = param("192.168.0.100", min_len=1,
                      doc="the UR controller's address (the simulated robot's fake UR: sim.host)")
    frequency: float = param(
        500.0, unit="Hz", ge=1.0, le=500.0, doc="RTDE frequency",
        why="RTDE runs at up to 500 Hz on e-Series; below 1 Hz it is no control link")
    speedj_acceleration: float = param(
        4.0, unit="rad/s^2", ge=0.1, le=UR_JOINT_ACCELERATION_MAX,
        doc="acceleration passed to speedJ",
        why="ur_rtde accepts up to 40 rad/s^2; below 0.1 the arm takes > 20 s to reach "
        "its speed limit")
    stop_deceleration: float = param(
        10.0, unit="rad/s^2", ge=1.0, le=UR_JOINT_ACCELERATION_MAX,
        doc="deceleration of speedStop on a fault",
        why="ur_rtde accepts up to 40 rad/s^2; at >= 1 a joint at 180 deg/s is at rest "
        "within pi s")
    stale_cycles: int = param(
        5, ge=1, le=10_000,
        doc="cycles without a new controller timestamp before a 'stale' fault",
        why="10 000 cycles is 20 s at 500 Hz, 8x ur_rtde's own 2.5 s detection: anything "
        "longer is no staleness check")
    hold_cycles: int = param(
        10, ge=1, le=10_000,
        doc="cycles without a new controller sample after which the command decelerates "
        "to rest (the arm's position is no longer known: no motion on a stale pose); "
        "the fault 'stale' follows at stale_cycles",
        why="from the next cycle to 20 s at 500 Hz (stale_cycles' own range)")
    watchdog_min_frequency: float = param(
        10.0, unit="Hz", ge=1.0, le=250.0,
        doc="the controller's RTDE watchdog (ur_rtde setWatchdog): the control script "
        "stops, and the arm with it, when the daemon sends nothing for longer than "
        "1 / this; the loop kicks it every cycle",
        why="the arm stops at most 1 s after the daemon goes quiet; above 250 Hz a 500 Hz "
        "loop's single late cycle would stop it",
    )
    connect_timeout: float = param(
        2.0, unit="s", ge=0.01, le=60.0,
        doc="how long connect() waits for the dashboard/RTDE ports and the first RTDE "
        "package before it reports that nothing answers",
        why="a controller on the LAN answers in ms; one silent for a minute is not there",
    )
