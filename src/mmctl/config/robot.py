"""`robot:` — the whole-body model: UR10e on the RB-KAIROS+ base, handle and sensor frames."""

from __future__ import annotations

import math

from mmctl.config.schema import param, section
from mmctl.errors import ConfigError

#: Preferred ("ergonomic") arm configuration [rad]: handle in front of the base at
#: roughly elbow height of a standing person.
DEFAULT_Q_DES = (0.0, -1.9, 1.9, -1.5708, -1.5708, 0.0)


@section
class RobotConfig:
    """Whole-body robot model parameters (SI units)."""

    base_mass: float = param(115.0, unit="kg", gt=0.0, doc="mobile base mass m_b (paper: 115 kg)")
    base_inertia_z: float = param(
        15.0, unit="kg m^2", gt=0.0,
        doc="base yaw inertia I_bz; estimate m(a^2+b^2)/12 for a 0.98 x 0.78 m box",
    )
    arm_mount: tuple[float, ...] = param(
        (0.0, 0.0, 0.56162), unit="m", shape=(3,), doc="arm base position in base_link"
    )
    arm_mount_yaw: float = param(
        math.pi, unit="rad",
        doc="yaw of the UR base (DH frame 0) about base_link z; pi: the arm's reach "
        "direction at shoulder_pan = 0 (DH -x) points forward (base +x)",
    )
    sensor_offset: tuple[float, ...] = param(
        (0.0, 0.0, 0.0254), unit="m", shape=(3,),
        doc="F/T sensor measurement frame origin in the UR flange (tool0) frame",
    )
    tool_offset: tuple[float, ...] = param(
        (0.0, 0.0, 0.18), unit="m", shape=(3,),
        doc="handle (end-effector) point in the flange frame; the controlled point",
    )
    q_des: tuple[float, ...] = param(
        DEFAULT_Q_DES, unit="rad", shape=(6,), doc="preferred arm configuration (null-space target)"
    )
    q_init: tuple[float, ...] | None = param(
        None, unit="rad / m", shape=(9,),
        doc="initial whole-body configuration (6 arm joints, base x, y, yaw) of the simulation; "
        "default: q_des and the base at the origin",
    )
    full_inertia: bool = param(
        False, doc="use the full coupled whole-body inertia instead of blockdiag(M_a, M_b)"
    )

    def validate(self, path: str, source: str | None) -> None:
        for i, q in enumerate(self.q_des):
            if abs(q) > 2.0 * math.pi:
                raise ConfigError(f"{path}.q_des[{i}]", q, "must lie within [-2pi, 2pi] rad", source)
