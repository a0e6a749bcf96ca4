"""`base:` — the RB-KAIROS+ omnidirectional base: geometry and drive link."""

from __future__ import annotations

from typing import Literal

from mmctl.config import can
from mmctl.config.schema import param, section, sub
from mmctl.errors import ConfigError


@section
class MecanumConfig:
    """Mecanum wheel geometry (RB-KAIROS+)."""

    wheel_radius: float = param(
        0.127, unit="m", ge=0.02, le=0.5,
        why="mecanum wheels of mobile bases are a few cm to 0.5 m in radius (RB-KAIROS+: "
        "0.127 m; 127 is millimetres)")
    half_length: float = param(
        0.21528, unit="m", ge=0.05, le=2.0, doc="wheel x offset from the centre",
        why="a base between a small cart and a 4 m vehicle (RB-KAIROS+: 0.215 m)")
    half_width: float = param(
        0.2690, unit="m", ge=0.05, le=2.0, doc="wheel y offset from the centre",
        why="a base between a small cart and a 4 m vehicle (RB-KAIROS+: 0.269 m)")
    wheel_signs: tuple[float, ...] = param(
        (1.0, 1.0, 1.0, 1.0), shape=(4,), ge=-1.0, le=1.0,
        doc="+1/-1 per wheel (FL, FR, BL, BR): drive direction as mounted",
        why="a direction: -1 or +1",
    )

    def validate(self, path: str, source: str | None) -> None:
        for i, sign in enumerate(self.wheel_signs):
            if sign not in (-1.0, 1.0):
                raise ConfigError(f"{path}.wheel_signs[{i}]", sign,
                                  "must be -1 or 1 (the wheel's drive direction)", source)


@section
class CanopenConfig:
    """Four CiA 402 drives on a CAN bus."""

    interface: str = can.interface()
    channel: str = can.channel("can1")
    host: str = can.host()
    port: int = can.port()
    bitrate: int = can.bitrate()
    node_ids: tuple[int, ...] = param((1, 2, 3, 4), shape=(4,), ge=1, le=127, doc="FL, FR, BL, BR",
                                      why="CANopen node ids are 1..127")
    heartbeat_timeout: float = param(
        0.1, unit="s", ge=0.002, le=5.0, doc="silent drive -> fault",
        why="a drive silent for seconds while its wheel may turn is no heartbeat check "
        "(5 s: tests that step the daemon by hand; 100, meant as ms, is caught)")
    heartbeat_period: float = param(
        0.02, unit="s", ge=0.001, le=1.0,
        doc="the producer heartbeat of the drives (0x1017) and of the daemon",
        why="0x1017 counts milliseconds; one beat a second is the slowest a 0.2 s watchdog "
        "can follow")
    counts_per_rev: int = param(
        4096, ge=100, le=1_000_000, doc="encoder counts per wheel revolution",
        why="a motor encoder behind a gearbox up to ~250:1; fewer than 100 counts cannot "
        "resolve a wheel's speed at 500 Hz")
    sdo_timeout: float = param(
        0.5, unit="s", ge=0.01, le=10.0,
        why="an SDO round trip takes ms on a 1 Mbit/s bus; a drive silent for 10 s is dead")
    master_node_id: int = param(127, ge=1, le=127, doc="node id of our heartbeat producer",
                                why="CANopen node ids are 1..127")
    stop_timeout: float = param(
        2.0, unit="s", ge=0.1, le=60.0,
        why="at least the ramp from the wheel speed limit to rest (checked at connect); a "
        "stop that takes a minute is no stop",
        doc="the longest a drive may take to bring its wheel to rest (shutdown, quick stop "
        "or fault reaction ramp): disable() and enable() wait at most this long; at least "
        "limits.wheel_velocity / (limits.base_linear_acceleration / wheel_radius)",
    )


@section
class SerialConfig:
    """Microcontroller bridge on a serial port."""

    port: str = param("/dev/ttyUSB0", min_len=1)
    baudrate: int = param(921600, ge=9600, le=12_000_000,
                          why="a 500 Hz frame exchange needs >= 9600 baud; USB-serial "
                          "bridges stop at 12 Mbaud")
    timeout: float = param(0.05, unit="s", ge=0.001, le=10.0,
                           why="a bridge answers within ms; one silent for 10 s is not there")
    link_timeout: float = param(
        0.1, unit="s", ge=0.002, le=5.0,
        doc="no valid frame from the bridge for this long -> base_link_lost",
        why="a bridge silent for seconds while the wheels may turn is no link check (5 s: "
        "tests on a loaded machine; 100, meant as ms, is caught)")


@section
class BaseConfig:
    """Omnidirectional base."""

    transport: Literal["canopen", "serial"] = param("canopen")
    process: bool = param(
        False,
        doc="run the transport in a process of its own that publishes odometry and the "
        "drives' health into a shared-memory mailbox and sends the loop's commands the "
        "moment they are left in another (docs/mailbox.md); false: the loop's own thread "
        "sends and reads",
        why="the loop then never waits on the base's link: a twist costs the loop a "
        "mailbox write and a wake-up instead of five CAN frames through the client "
        "library")
    mecanum: MecanumConfig = sub(MecanumConfig)
    canopen: CanopenConfig = sub(CanopenConfig)
    serial: SerialConfig = sub(SerialConfig)
    command_watchdog: float = param(
        0.2, unit="s", ge=0.01, le=10.0,
        doc="each drive quick-stops by itself when the master's heartbeat (consumer "
        "heartbeat 0x1016) or the target RPDO (deadline 0x1400:05) is missing this long",
        why="the vendor's 0.2 s; a base that rolls on for more than 10 s after the daemon "
        "died has no watchdog (200, meant as ms, is caught)",
    )

    def validate(self, path: str, source: str | None) -> None:
        co = self.canopen
        if not co.heartbeat_timeout > co.heartbeat_period:
            key = f"{path}.canopen.heartbeat_timeout" if path else "canopen.heartbeat_timeout"
            raise ConfigError(
                key, co.heartbeat_timeout,
                f"must be > base.canopen.heartbeat_period = {co.heartbeat_period:g} s (a "
                "drive beating on time would be 'silent')", source)
        hb = self.canopen.heartbeat_period
        if self.command_watchdog < 2.0 * hb:
            key = f"{path}.command_watchdog" if path else "command_watchdog"
            raise ConfigError(
                key, self.command_watchdog,
                f"must be at least 2 x base.canopen.heartbeat_period = {2.0 * hb:g} s "
                "(the drives watch the master's heartbeat with it)", source,
            )
