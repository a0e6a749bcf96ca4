"""The simulated whole-body plant: UR10e joints and the omnidirectional base.

Each commanded velocity goes through a first-order lag (time constant ``tau``,
discretised exactly: ``v += (1 - exp(-dt/tau)) (v_cmd - v)``) whose per-cycle change
is then clipped to an acceleration limit:

* arm: per joint, ``|dq̇_i| <= a_i dt`` (the UR's joint acceleration limit, the ``acc``
  of speedJ);
* base: the linear part as a vector (``||d(v_x, v_y)|| <= a_lin dt``, direction kept)
  and the yaw rate on its own (``|dω| <= a_ang dt``), limits from ``cfg.limits``.

Positions are integrated with the new (actual) velocities (semi-implicit Euler); the
base twist is in the base frame, so the world pose integrates it rotated by the
mid-step yaw.  The actual velocities are what :func:`mmctl.control` energy metrics
must use.

Coordinates: ``q = (q_1..q_6 [rad], x_b, y_b [m], yaw_b [rad])`` (base pose in the
world), ``q̇ = (q̇_1..q̇_6 [rad/s], v_x, v_y [m/s], ω_z [rad/s])`` (base twist in the
base frame) — the same layout as the controller's measured ``q``/``q̇``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

Vec = NDArray[np.float64]


@dataclass(frozen=True)
class PlantParams:
    """Dynamics of the simulated robot (SI units).

    arm_tau: arm joint velocity lag time constant [s] (0 = none);
    arm_acceleration: (6,) joint acceleration limits [rad/s^2];
    base_tau: base twist lag time constant [s] (0 = none); the drives' velocity loops
    and the 115 kg base respond much slower than the arm;
    base_linear_acceleration [m/s^2], base_angular_acceleration [rad/s^2].
    """

    arm_tau: float = 0.02
    arm_acceleration: tuple[float, ...] = (4.0,) * 6
    base_tau: float = 0.12
    base_linear_acceleration: float = 3.0
    base_angular_acceleration: float = 3.0

    def __post_init__(self) -> None:
        if self.arm_tau < 0.0 or self.base_tau < 0.0:
            raise ValueError("time constants must be >= 0 s")
        if len(self.arm_acceleration) != 6 or min(self.arm_acceleration) <= 0.0:
            raise ValueError("arm_acceleration must be 6 values > 0 rad/s^2")
        if self.base_linear_acceleration <= 0.0 or self.base_angular_acceleration <= 0.0:
            raise ValueError("base accelerations must be > 0")

    @classmethod
    def from_config(cls, cfg: object, arm_tau: float = 0.02, base_tau: float = 0.12) -> PlantParams:
        """Acceleration limits from ``cfg.limits`` (a :class:`mmctl.config.Config`)."""
        lim = cfg.limits  # type: ignore[attr-defined]
        return cls(
            arm_tau=arm_tau,
            arm_acceleration=tuple(float(a) for a in lim.joint_acceleration),
            base_tau=base_tau,
            base_linear_acceleration=float(lim.base_linear_acceleration),
            base_angular_acceleration=float(lim.base_angular_acceleration),
        )


class PlantState(NamedTuple):
    """Actual whole-body configuration ``q`` (9,) and velocity ``qd`` (9,) (layout above)."""

    q: Vec
    qd: Vec


def initial_state(q0: ArrayLike) -> PlantState:
    """The robot at rest at ``q0`` (9,)."""
    q = np.array(q0, dtype=float)
    if q.shape != (9,):
        raise ValueError(f"q0 must have shape (9,), got {q.shape}")
    return PlantState(q, np.zeros(9))


def _lag(tau: float, dt: float) -> float:
    return 1.0 if tau <= 0.0 else 1.0 - math.exp(-dt / tau)


class Plant:
    """Integrates commanded arm joint velocities and base twists (see module doc).

    ``step`` is deterministic and allocation-light; the lag factors are computed once
    per distinct ``dt``.
    """

    def __init__(self, params: PlantParams) -> None:
        self.params = params
        self._arm_acc = np.asarray(params.arm_acceleration, dtype=float)
        self._dt = -1.0
        self._arm_k = 1.0
        self._base_k = 1.0

    def step(self, state: PlantState, qd_arm_cmd: ArrayLike, base_cmd: ArrayLike, dt: float) -> PlantState:
        """Advance by ``dt`` [s] under the commanded arm joint velocities (6,) [rad/s] and
        base twist (3,) (v_x, v_y [m/s], ω_z [rad/s], base frame); returns the new state."""
        if dt <= 0.0:
            raise ValueError(f"dt must be > 0 s, got {dt}")
        p = self.params
        if dt != self._dt:
            self._dt = dt
            self._arm_k = _lag(p.arm_tau, dt)
            self._base_k = _lag(p.base_tau, dt)
        qd_old = state.qd
        qd = np.empty(9)
        # arm: lag then per-joint acceleration clip
        dv = self._arm_k * (np.asarray(qd_arm_cmd, dtype=float) - qd_old[:6])
        lim = self._arm_acc * dt
        qd[:6] = qd_old[:6] + np.clip(dv, -lim, lim)
        # base: lag, then the linear acceleration as a vector and the yaw rate alone
        b = np.asarray(base_cmd, dtype=float)
        kb = self._base_k
        dvx = kb * (b[0] - qd_old[6])
        dvy = kb * (b[1] - qd_old[7])
        dw = kb * (b[2] - qd_old[8])
        dlin = math.hypot(dvx, dvy)
        lin_max = p.base_linear_acceleration * dt
        if dlin > lin_max:
            s = lin_max / dlin
            dvx *= s
            dvy *= s
        ang_max = p.base_angular_acceleration * dt
        dw = min(max(dw, -ang_max), ang_max)
        qd[6] = qd_old[6] + dvx
        qd[7] = qd_old[7] + dvy
        qd[8] = qd_old[8] + dw
        # integrate
        q = state.q.copy()
        q[:6] += qd[:6] * dt
        yaw_mid = q[8] + 0.5 * qd[8] * dt
        c, s_ = math.cos(yaw_mid), math.sin(yaw_mid)
        q[6] += (c * qd[6] - s_ * qd[7]) * dt
        q[7] += (s_ * qd[6] + c * qd[7]) * dt
        q[8] += qd[8] * dt
        return PlantState(q, qd)
