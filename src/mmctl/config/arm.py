"""`arm:` — the UR10e link (ur_rtde)."""

from __future__ import annotations

from mmctl.config.schema import param, section


@section
class ArmConfig:
    """UR10e connection and command parameters."""

    host: str = param("127.0.0.2", min_len=1, doc="controller address (the fake UR in simulation)")
    frequency: float = param(500.0, unit="Hz", gt=0.0, le=500.0, doc="RTDE frequency")
    speedj_acceleration: float = param(
        4.0, unit="rad/s^2", gt=0.0, le=40.0, doc="acceleration passed to speedJ"
    )
    stop_deceleration: float = param(
        10.0, unit="rad/s^2", gt=0.0, le=40.0, doc="deceleration of speedStop on a fault"
    )
    stale_cycles: int = param(
        5, gt=0, doc="cycles without a new controller timestamp before a 'stale' fault"
    )
    watchdog_min_frequency: float = param(
        10.0, unit="Hz", ge=1.0, le=250.0,
        doc="the controller's RTDE watchdog (ur_rtde setWatchdog): the control script "
        "stops, and the arm with it, when the daemon sends nothing for longer than "
        "1 / this; the loop kicks it every cycle",
    )
    connect_timeout: float = param(
        2.0, unit="s", gt=0.0, le=60.0,
        doc="how long connect() waits for the dashboard/RTDE ports and the first RTDE "
        "package before it reports that nothing answers",
    )
