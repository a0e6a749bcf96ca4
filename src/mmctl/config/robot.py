"""`robot:` — the whole-body model: UR10e on the RB-KAIROS+ base, handle and sensor frames."""

from __future__ import annotations

import math

from mmctl.config.schema import param, section

#: Preferred ("ergonomic") arm configuration [rad]: handle in front of the base at
#: roughly elbow height of a standing person.
DEFAULT_Q_DES = (0.0, -1.9, 1.9, -1.5708, -1.5708, 0.0)
_TWO_PI = 6.2832  # [rad] 2 pi rounded up: the UR10e's +-360 deg


@section
class RobotConfig:
    """Whole-body robot model parameters (SI units)."""

    base_mass: float = param(
        115.0, unit="kg", ge=10.0, le=1000.0, doc="mobile base mass m_b (paper: 115 kg)",
        why="a base that carries a 33 kg UR10e: from a light cart to a ton (115 000 is grams)")
    base_inertia_z: float = param(
        15.0, unit="kg m^2", ge=0.1, le=2000.0,
        doc="base yaw inertia I_bz; estimate m(a^2+b^2)/12 for a 0.98 x 0.78 m box",
        why="up to a ton on a 3 x 3 m footprint: m (a^2 + b^2) / 12 = 1500 kg m^2",
    )
    arm_mount: tuple[float, ...] = param(
        (0.0, 0.0, 0.56162), unit="m", shape=(3,), ge=-2.0, le=2.0,
        doc="arm base position in base_link",
        why="on the base, within 2 m of its centre (561.62 is millimetres)",
    )
    arm_mount_yaw: float = param(
        math.pi, unit="rad", ge=-_TWO_PI, le=_TWO_PI,
        doc="yaw of the UR base (DH frame 0) about base_link z; pi: the arm's reach "
        "direction at shoulder_pan = 0 (DH -x) points forward (base +x)",
        why="an angle in radians (180 is degrees)",
    )
    sensor_offset: tuple[float, ...] = param(
        (0.0, 0.0, 0.0254), unit="m", shape=(3,), ge=-0.5, le=0.5,
        doc="F/T sensor measurement frame origin in the UR flange (tool0) frame",
        why="a sensor on the flange, within 0.5 m of it (25.4 is millimetres)",
    )
    sensor_rotation: tuple[float, ...] = param(
        (0.0, 0.0, 0.0), unit="rad", shape=(3,), ge=-_TWO_PI, le=_TWO_PI,
        doc="the F/T sensor's axes relative to the flange's as roll, pitch, yaw about the "
        "flange's x, y, z (URDF rpy: R_flange_sensor = Rz(yaw) Ry(pitch) Rx(roll)); the "
        "sensor reports its wrench in these axes (e.g. [0, 0, 0.5236]: mounted turned "
        "30 deg about the flange's z); sensor.wrench.handle_com is in them",
        why="angles in radians (90 or 180 are degrees)",
    )
    tool_offset: tuple[float, ...] = param(
        (0.0, 0.0, 0.18), unit="m", shape=(3,), ge=-1.0, le=1.0,
        doc="handle (end-effector) point in the flange frame; the controlled point",
        why="a handle within 1 m of the flange (180 is millimetres)",
    )
    q_des: tuple[float, ...] = param(
        DEFAULT_Q_DES, unit="rad", shape=(6,), ge=-_TWO_PI, le=_TWO_PI,
        doc="preferred arm configuration (null-space target)",
        why="the UR10e's joints turn +-360 deg (in radians)",
    )
    q_init: tuple[float, ...] | None = param(
        None, unit="rad / m", shape=(9,),
        ge=(-_TWO_PI,) * 6 + (-1000.0, -1000.0, -_TWO_PI),
        le=(_TWO_PI,) * 6 + (1000.0, 1000.0, _TWO_PI),
        doc="initial whole-body configuration (6 arm joints, base x, y, yaw) of the simulation; "
        "default: q_des and the base at the origin",
        why="joints within +-360 deg; the base within a km of the origin",
    )
    full_inertia: bool = param(
        False, doc="use the full coupled whole-body inertia instead of blockdiag(M_a, M_b)"
    )

