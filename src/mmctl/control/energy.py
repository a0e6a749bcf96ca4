"""Kinetic energy of the mobile manipulator (paper eq. 10)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

Vec = NDArray[np.float64]


class Energy(NamedTuple):
    """Kinetic energy [J]: ``total = arm + base`` for the block-diagonal model."""

    total: float
    arm: float
    base: float

    def base_share(self) -> float:
        """base / total (0 when at rest)."""
        return self.base / self.total if self.total > 0.0 else 0.0


def kinetic_energy(M_a: Vec, M_b: Vec, qdot: Vec) -> Energy:
    """E_K = qd_a^T M_a qd_a / 2 + qd_b^T M_b qd_b / 2.

    M_a: (6, 6) arm inertia; M_b: (3,) diagonal or (3, 3) base inertia; qdot: (9,)
    (arm joint rates [rad/s], base twist in the base frame [m/s, m/s, rad/s]).
    """
    qa = qdot[:6]
    arm = 0.5 * float(qa @ (M_a @ qa))
    qb = qdot[6:9]
    if M_b.ndim == 1:
        b = (M_b * qb * qb).tolist()
        base = 0.5 * (b[0] + b[1] + b[2])
    else:
        base = 0.5 * float(qb @ (M_b @ qb))
    return Energy(arm + base, arm, base)


def kinetic_energy_full(M: Vec, qdot: Vec) -> float:
    """E_K = qdot^T M qdot / 2 for any (n, n) inertia (e.g. the coupled 9x9) [J]."""
    return 0.5 * float(qdot @ M @ qdot)
