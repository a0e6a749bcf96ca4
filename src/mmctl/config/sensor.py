"""`sensor:` — the ATI Axia80 force/torque sensor link and the wrench processing."""

from __future__ import annotations

from typing import Literal

from mmctl.config import can
from mmctl.config.schema import param, section, sub
from mmctl.errors import ConfigError


@section
class SensorCanConfig:
    """ATI Net F/T CAN layout on any python-can interface."""

    interface: str = can.interface()
    channel: str = can.channel("can0")
    host: str = can.host()
    port: int = can.port()
    bitrate: int = can.bitrate()
    base_id: int = param(0x20, ge=0, le=0x7F, doc="CAN base id; frame id = (base_id << 4) | opcode",
                         why="(base_id << 4) | opcode is an 11-bit CAN id")
    timeout: float = param(
        0.005, unit="s", ge=0.0005, le=0.1, doc="reply timeout of one read",
        why="the reply's two frames take ~0.3 ms on a 1 Mbit/s bus; the read waits inside "
        "the cycle, so 100 ms (50 periods at 500 Hz) is the most a cycle can be held")
    connect_timeout: float = param(
        0.5, unit="s", ge=0.01, le=30.0, doc="reply timeout of the calibration reads at connect",
        why="a sensor answers in ms; one silent for 30 s is not there",
    )
    status_saturation_mask: int = param(
        0x0006, ge=0, le=0xFFFF, why="bits of the 16-bit status word",
        doc="status bits meaning gauge saturation (any other set bit is a status fault)",
    )


@section
class SensorRdtConfig:
    """ATI RDT over UDP (Axia80 Ethernet)."""

    host: str = param("127.0.0.1", min_len=1)
    port: int = param(49152, ge=1, le=65535, why="a UDP port")
    counts_per_force: float = param(
        1.0e6, ge=1.0, le=1e9, unit="counts/N",
        why="int32 counts: from 1 count/N to 1e9 (a 2 N range)")
    counts_per_torque: float = param(
        1.0e6, ge=1.0, le=1e9, unit="counts/(N m)",
        why="int32 counts: from 1 count/N m to 1e9 (a 2 N m range)")
    connect_timeout: float = param(
        0.5, unit="s", ge=0.01, le=30.0, doc="wait for the first record",
        why="a sensor answers in ms; one silent for 30 s is not there")
    restart_after: float = param(
        0.1, unit="s", ge=0.005, le=10.0,
        doc="no record for this long: send the start request again (a rebooted sensor "
            "streams only after one), then at doubling intervals up to 1 s; the stale "
            "fault is sensor.wrench.stale_timeout's",
        why="from a few RDT periods to 10 s (a sensor's reboot takes seconds)")
    status_error_mask: int = param(
        0x80000000, ge=0, le=0xFFFFFFFF, doc="status bits that are a status fault",
        why="bits of the 32-bit RDT status word"
    )
    status_saturation_mask: int = param(
        0x00020000, ge=0, le=0xFFFFFFFF, doc="status bits meaning gauge saturation",
        why="bits of the 32-bit RDT status word"
    )


@section
class WrenchConfig:
    """Processing shared by all sensor transports."""

    tare_samples: int = param(
        100, ge=1, le=10_000, doc="samples averaged by a software tare",
        why="the person lets go during a tare: 10 000 samples is 20 s at 500 Hz")
    handle_mass: float = param(
        0.6, unit="kg", ge=0.0, le=12.5, doc="mass below the sensor (handle, peg)",
        why="the UR10e's payload is 12.5 kg (600 is grams)")
    handle_com: tuple[float, ...] = param(
        (0.0, 0.0, 0.08), unit="m", shape=(3,), ge=-0.5, le=0.5,
        doc="its centre of mass in the sensor frame",
        why="a handle within 0.5 m of the sensor (80 is millimetres)",
    )
    deadband_force: float = param(
        2.0, unit="N", ge=0.0, le=20.0,
        why="a person guides with 10-15 N: a wider dead band swallows the guidance")
    deadband_torque: float = param(
        0.2, unit="N m", ge=0.0, le=2.0,
        why="a person's guiding torque is ~1 N m: a wider dead band swallows it")
    lowpass_cutoff: float = param(
        20.0, unit="Hz", ge=0.1, le=500.0, doc="first-order low-pass cut-off",
        why="a hand's force changes within 0.1-10 Hz; 500 Hz is the Nyquist rate of a "
        "1 kHz loop")
    axis_mask: tuple[bool, ...] = param(
        (True, True, True, False, False, False), shape=(6,),
        doc="which wrench axes drive the admittance (paper: orientation held fixed)",
    )
    force_limit: float = param(
        150.0, unit="N", ge=1.0, le=500.0, doc="|f| above this is a fault",
        why="the Axia80 M20 senses +-500 N (x, y): a higher limit could never trip")
    torque_limit: float = param(
        15.0, unit="N m", ge=0.1, le=20.0, doc="|t| above this is a fault",
        why="the Axia80 M20 senses +-20 N m: a higher limit could never trip")
    stale_timeout: float = param(
        0.010, unit="s", ge=0.001, le=5.0, doc="no new sample for longer: fault",
        why="the robot follows the last sample until then: 10 ms on the robot, 5 s for "
        "tests that step the daemon by hand; 10 (10 ms without its unit) is caught")
    range_force: tuple[float, ...] = param(
        (500.0, 500.0, 900.0), unit="N", shape=(3,), ge=1.0, le=2000.0,
        doc="sensing range |Fx|, |Fy|, |Fz| (ATI Axia80 M20); beyond it: saturation fault",
        why="the M20's 500/900 N with room for stronger calibrations (500 000 is mN)",
    )
    range_torque: tuple[float, ...] = param(
        (20.0, 20.0, 20.0), unit="N m", shape=(3,), ge=0.1, le=100.0,
        doc="sensing range |Tx|, |Ty|, |Tz| (ATI Axia80 M20); beyond it: saturation fault",
        why="the M20's 20 N m with room for stronger calibrations (20 000 is N mm)",
    )

    def validate(self, path: str, source: str | None) -> None:
        if self.deadband_force >= self.force_limit:
            raise ConfigError(f"{path}.deadband_force", self.deadband_force,
                              f"must be < force_limit = {self.force_limit:g} N", source)
        if self.deadband_torque >= self.torque_limit:
            raise ConfigError(f"{path}.deadband_torque", self.deadband_torque,
                              f"must be < torque_limit = {self.torque_limit:g} N m", source)


@section
class ToolCalibrationConfig:
    """`mmctl calibrate tool`: with hands off, the armed robot turns its wrist through
    orientations, weighs the handle at each and fits the sensor bias, the handle's mass
    and centre of mass (docs/hand-guiding.md).  Wrist joints only, the base held still;
    any force on the handle stops it."""

    poses: int = param(
        8, ge=4, le=50,
        doc="orientations weighed (the start pose and two short probe tilts among them); "
        "`--poses` overrides it",
        why="10 unknowns need 3 orientations, a least squares fit a few more; 50 take "
        "about 10 minutes")
    speed: float = param(
        0.3, unit="rad/s", gt=0.0, le=1.0,
        doc="top speed of each wrist joint (lower where the handle would pass the "
        "end-effector cap; never above limits.joint_velocity)",
        why="at 0.3 rad/s the handle moves at about 0.1 m/s; 1 rad/s (tests) is the most "
        "an automatic motion next to a person gets here")
    acceleration: float = param(
        0.5, unit="rad/s^2", gt=0.0, le=4.0,
        doc="the motion's ramps (never above limits.joint_acceleration)",
        why="4 rad/s^2 is the UR10e's default speedJ acceleration")
    wrist_range: tuple[float, ...] = param(
        (0.5, 1.3, 3.1416), unit="rad", shape=(3,), ge=0.0, le=3.1416,
        doc="how far wrist 1, wrist 2 and wrist 3 may turn from the start pose (wrist 1, "
        "which moves the whole wrist, only slightly); the handle must be free to sweep "
        "this range",
        why="half a turn each way at most (90 is degrees)")
    probe: float = param(
        0.2, unit="rad", ge=0.05, le=1.0,
        doc="the first two poses tilt gravity by at most this much from the start, so "
        "the push check below has weighed this handle before the wrist turns far",
        why="from 3 to 57 deg (20 is degrees)")
    settle_time: float = param(
        0.5, unit="s", ge=0.0, le=10.0,
        doc="the arm rests this long at a pose before its wrench is averaged",
        why="a wrist at rest settles within a few hundred ms; 10 s is a stuck arm")
    average_time: float = param(
        0.5, unit="s", ge=0.02, le=10.0, doc="the raw wrench is averaged this long per pose",
        why="at least ten samples at 500 Hz; 10 s is beyond any sensor noise (500 is ms)")
    abort_force: float = param(
        5.0, unit="N", ge=0.5, le=50.0,
        doc="a force this far from the weight predicted from the poses weighed so far "
        "(the configured handle_mass and handle_com to begin with) is a hand on the "
        "handle: the robot stops and is disarmed",
        why="above the sensor's noise and a cable's pull; a hand pushes 10-15 N")
    abort_torque: float = param(
        0.5, unit="N m", ge=0.05, le=5.0,
        doc="the same for the torque",
        why="above the sensor's noise; a hand's guiding torque is about 1 N m")


@section
class SensorConfig:
    """Force/torque sensor."""

    transport: Literal["can", "rdt"] = param("can")
    process: bool = param(
        True,
        doc="run the transport in a process of its own that polls the sensor phased to the "
        "loop and leaves each sample in a shared-memory mailbox: the loop never waits for "
        "the sensor (docs/mailbox.md); false: the loop's own thread asks and reads (also "
        "with python-can's in-process `virtual` interface, which no other process reaches)",
        why="a request/reply sensor's round trip (CAN over socketcand: 0.4 ms p50, 1.4 ms "
        "p99 here) is then off the loop's time")
    process_lead: float = param(
        0.001, unit="s", gt=0.0, le=0.01,
        doc="with `process`: how long before each cycle's deadline the sensor's process "
        "asks a request/reply sensor for its sample (its round trip's p90-p99 plus 0.1 ms; "
        "measure with tools/sensor_link_bench.py); capped at half the loop's period",
        why="10 ms is five periods at 500 Hz: a sample that old is stale")
    can: SensorCanConfig = sub(SensorCanConfig)
    rdt: SensorRdtConfig = sub(SensorRdtConfig)
    wrench: WrenchConfig = sub(WrenchConfig)
    calibration: ToolCalibrationConfig = sub(ToolCalibrationConfig)
