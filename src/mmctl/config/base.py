"""`base:` — the RB-KAIROS+ omnidirectional base: geometry and drive link."""

from __future__ import annotations

from typing import Literal

from mmctl.config import can
from mmctl.config.schema import param, section, sub
from mmctl.errors import ConfigError


@section
class MecanumConfig:
    """Mecanum wheel geometry (RB-KAIROS+)."""

    wheel_radius: float = param(0.127, unit="m", gt=0.0)
    half_length: float = param(0.21528, unit="m", gt=0.0, doc="wheel x offset from the centre")
    half_width: float = param(0.2690, unit="m", gt=0.0, doc="wheel y offset from the centre")
    wheel_signs: tuple[float, ...] = param(
        (1.0, 1.0, 1.0, 1.0), shape=(4,),
        doc="+1/-1 per wheel (FL, FR, BL, BR): drive direction as mounted",
    )


@section
class CanopenConfig:
    """Four CiA 402 drives on a CAN bus."""

    interface: str = can.interface()
    channel: str = can.channel("mmctl-base")
    host: str = can.host()
    port: int = can.port()
    bitrate: int = can.bitrate()
    node_ids: tuple[int, ...] = param((1, 2, 3, 4), shape=(4,), ge=1, le=127, doc="FL, FR, BL, BR")
    heartbeat_timeout: float = param(0.1, unit="s", gt=0.0, doc="silent drive -> fault")
    heartbeat_period: float = param(0.02, unit="s", gt=0.0, doc="our producer heartbeat")
    counts_per_rev: int = param(4096, gt=0, doc="encoder counts per wheel revolution")
    sdo_timeout: float = param(0.5, unit="s", gt=0.0)
    master_node_id: int = param(127, ge=1, le=127, doc="node id of our heartbeat producer")
    stop_timeout: float = param(
        2.0, unit="s", gt=0.0, le=60.0,
        doc="the longest a drive may take to bring its wheel to rest (shutdown, quick stop "
        "or fault reaction ramp): disable() and enable() wait at most this long; at least "
        "limits.wheel_velocity / (limits.base_linear_acceleration / wheel_radius)",
    )


@section
class SerialConfig:
    """Microcontroller bridge on a serial port."""

    port: str = param("/dev/ttyUSB0", min_len=1)
    baudrate: int = param(921600, gt=0)
    timeout: float = param(0.05, unit="s", gt=0.0)
    link_timeout: float = param(
        0.1, unit="s", gt=0.0, doc="no valid frame from the bridge for this long -> base_link_lost"
    )


@section
class BaseConfig:
    """Omnidirectional base."""

    transport: Literal["canopen", "serial"] = param("canopen")
    mecanum: MecanumConfig = sub(MecanumConfig)
    canopen: CanopenConfig = sub(CanopenConfig)
    serial: SerialConfig = sub(SerialConfig)
    command_watchdog: float = param(
        0.2, unit="s", gt=0.0, le=65.535,
        doc="each drive quick-stops by itself when the master's heartbeat (consumer "
        "heartbeat 0x1016) or the target RPDO (deadline 0x1400:05) is missing this long",
    )

    def validate(self, path: str, source: str | None) -> None:
        hb = self.canopen.heartbeat_period
        if self.command_watchdog < 2.0 * hb:
            key = f"{path}.command_watchdog" if path else "command_watchdog"
            raise ConfigError(
                key, self.command_watchdog,
                f"must be at least 2 x base.canopen.heartbeat_period = {2.0 * hb:g} s "
                "(the drives watch the master's heartbeat with it)", source,
            )
