"""`robot:` — the whole-body model: UR10e on the RB-KAIROS+ base, handle and sensor frames."""

from __future__ import annotations

import math

from mmctl.config.schema import param, section
from mmctl.errors import ConfigError

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
    # -- the body's collision shapes (docs/hand-guiding.md, "The robot's body") --------
    link_radii: tuple[float, ...] = param(
        (0.0764, 0.0764, 0.058, 0.047, 0.047, 0.0445), unit="m", shape=(6,), ge=0.01, le=0.3,
        doc="radius of the capsule around each UR10e link (shoulder, upper arm, forearm, "
        "wrist 1, wrist 2, wrist 3); default: the largest cross-section of UR's own "
        "collision meshes (ur_description, meshes/ur10e/collision)",
        why="from a 1 cm rod to a 30 cm housing (76.4 is millimetres)")
    sensor_radius: float = param(
        0.041, unit="m", ge=0.01, le=0.2,
        doc="radius of the F/T sensor's body (ATI Axia80: 82 mm across); its height is "
        "sensor_offset's z",
        why="a sensor within 20 cm of the flange axis (41 is millimetres)")
    handle_radius: float = param(
        0.05, unit="m", ge=0.005, le=0.3,
        doc="radius of the capsule from the sensor to the handle point (tool_offset): the "
        "handle and the hand around it",
        why="a bare rod to a two-handed grip (50 is millimetres)")
    deck_size: tuple[float, ...] = param(
        (0.978, 0.776, 0.56), unit="m", shape=(3,), ge=(0.1, 0.1, 0.05), le=(3.0, 3.0, 2.0),
        doc="the base's body as a box from the floor up (length x, width y, height z) in "
        "base_link; the arm stands on its top (arm_mount's z >= the height)",
        why="a cart's footprint up to 3 x 3 m, up to 2 m tall (978 is millimetres)")
    deck_center: tuple[float, ...] = param(
        (0.0, 0.0), unit="m", shape=(2,), ge=-2.0, le=2.0,
        doc="the deck box's centre (x, y) in base_link",
        why="within 2 m of base_link (the deck carries the arm)")
    cabinet_size: tuple[float, ...] = param(
        (0.0, 0.0, 0.0), unit="m", shape=(3,), ge=0.0, le=3.0,
        doc="a mast or cabinet on the deck as a box (x, y, z sizes); all zero: none",
        why="up to 3 m on a side; 0 switches it off")
    cabinet_center: tuple[float, ...] = param(
        (0.0, 0.0, 0.0), unit="m", shape=(3,), ge=-3.0, le=3.0,
        doc="the cabinet box's centre in base_link",
        why="on or next to the base, within 3 m of base_link")

    def validate(self, path: str, source: str | None) -> None:
        if self.arm_mount[2] < self.deck_size[2] - 1e-9:
            raise ConfigError(f"{path}.deck_size" if path else "deck_size", self.deck_size,
                              f"its height {self.deck_size[2]:g} m must not exceed the arm's "
                              f"mount height arm_mount z = {self.arm_mount[2]:g} m (the arm "
                              "stands on the deck)", source)

