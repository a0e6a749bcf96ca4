"""`sensor:` — the ATI Axia80 force/torque sensor link and the wrench processing."""

from __future__ import annotations

from typing import Literal

from mmctl.config import can
from mmctl.config.schema import param, section, sub


@section
class SensorCanConfig:
    """ATI Net F/T CAN layout on any python-can interface."""

    interface: str = can.interface()
    channel: str = can.channel("mmctl-sensor")
    host: str = can.host()
    port: int = can.port()
    bitrate: int = can.bitrate()
    base_id: int = param(0x20, ge=0, le=0x7F, doc="CAN base id; frame id = (base_id << 4) | opcode")
    timeout: float = param(0.005, unit="s", gt=0.0, doc="reply timeout of one read")
    connect_timeout: float = param(
        0.5, unit="s", gt=0.0, doc="reply timeout of the calibration reads at connect"
    )
    status_saturation_mask: int = param(
        0x0006, ge=0, le=0xFFFF,
        doc="status bits meaning gauge saturation (any other set bit is a status fault)",
    )


@section
class SensorRdtConfig:
    """ATI RDT over UDP (Axia80 Ethernet)."""

    host: str = param("127.0.0.1", min_len=1)
    port: int = param(49152, gt=0, le=65535)
    counts_per_force: float = param(1.0e6, gt=0.0, unit="counts/N")
    counts_per_torque: float = param(1.0e6, gt=0.0, unit="counts/(N m)")
    connect_timeout: float = param(0.5, unit="s", gt=0.0, doc="wait for the first record")
    restart_after: float = param(
        0.1, unit="s", gt=0.0, le=10.0,
        doc="no record for this long: send the start request again (a rebooted sensor "
            "streams only after one), then at doubling intervals up to 1 s; the stale "
            "fault is sensor.wrench.stale_timeout's",
    )
    status_error_mask: int = param(
        0x80000000, ge=0, le=0xFFFFFFFF, doc="status bits that are a status fault"
    )
    status_saturation_mask: int = param(
        0x00020000, ge=0, le=0xFFFFFFFF, doc="status bits meaning gauge saturation"
    )


@section
class WrenchConfig:
    """Processing shared by all sensor transports."""

    tare_samples: int = param(100, gt=0, doc="samples averaged by a software tare")
    handle_mass: float = param(0.6, unit="kg", ge=0.0, doc="mass below the sensor (handle, peg)")
    handle_com: tuple[float, ...] = param(
        (0.0, 0.0, 0.08), unit="m", shape=(3,), doc="its centre of mass in the sensor frame"
    )
    deadband_force: float = param(2.0, unit="N", ge=0.0)
    deadband_torque: float = param(0.2, unit="N m", ge=0.0)
    lowpass_cutoff: float = param(20.0, unit="Hz", gt=0.0, doc="first-order low-pass cut-off")
    axis_mask: tuple[bool, ...] = param(
        (True, True, True, False, False, False), shape=(6,),
        doc="which wrench axes drive the admittance (paper: orientation held fixed)",
    )
    force_limit: float = param(150.0, unit="N", gt=0.0, doc="|f| above this is a fault")
    torque_limit: float = param(15.0, unit="N m", gt=0.0, doc="|t| above this is a fault")
    stale_timeout: float = param(0.010, unit="s", gt=0.0, doc="no new sample for longer: fault")
    range_force: tuple[float, ...] = param(
        (500.0, 500.0, 900.0), unit="N", shape=(3,), gt=0.0,
        doc="sensing range |Fx|, |Fy|, |Fz| (ATI Axia80 M20); beyond it: saturation fault",
    )
    range_torque: tuple[float, ...] = param(
        (20.0, 20.0, 20.0), unit="N m", shape=(3,), gt=0.0,
        doc="sensing range |Tx|, |Ty|, |Tz| (ATI Axia80 M20); beyond it: saturation fault",
    )


@section
class SensorConfig:
    """Force/torque sensor."""

    transport: Literal["can", "rdt"] = param("can")
    can: SensorCanConfig = sub(SensorCanConfig)
    rdt: SensorRdtConfig = sub(SensorRdtConfig)
    wrench: WrenchConfig = sub(WrenchConfig)
