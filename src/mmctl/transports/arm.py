"""The arm seam: what the daemon needs from a UR10e link, whatever carries it."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from mmctl.types import ArmState


@runtime_checkable
class Arm(Protocol):
    """A robot arm commanded in joint speed (see :class:`~mmctl.transports.ur_rtde_arm.UrRtdeArm`).

    Health is judged by :meth:`read_state`: it raises
    :class:`~mmctl.errors.SafetyFault` naming the cause (``ARM_DISCONNECTED``,
    ``ARM_EMERGENCY_STOP``, ``ARM_PROTECTIVE_STOP``, ``ARM_NOT_PLAYING``, ``ARM_STALE``).
    """

    def connect(self) -> None:
        """Open the link (all I/O happens here, never in ``__init__``)."""

    def read_state(self) -> ArmState:
        """The newest sample: q [rad], qd [rad/s], controller time [s], runtime state,
        safety status bits; raises SafetyFault when the arm is not fit to move."""
        ...

    def speed_j(self, qd: NDArray[np.float64], acceleration: float | None = None,
                dt: float | None = None) -> object:
        """Command joint speeds qd (6,) [rad/s] (clamped to the joint speed limits) with
        leading-axis acceleration [rad/s^2], valid for dt [s]."""
        ...

    def kick_watchdog(self) -> None:
        """Keep the controller's communication watchdog fed in a cycle without a
        speed_j (a daemon that goes quiet gets the arm stopped by the controller)."""

    def stop(self, deceleration: float | None = None) -> None:
        """Bring the joints to rest with ``deceleration`` [rad/s^2]; never blocks long."""

    def reconnect(self) -> None:
        """Close and open the link again (after a fault, on an operator's request)."""

    def close(self) -> None:
        """Stop, end the controller program and disconnect (idempotent)."""

    def digital_input(self, index: int) -> bool:
        """The controller's digital input ``index`` (0-7 standard, 8-15 configurable,
        16-17 tool)."""
        ...
