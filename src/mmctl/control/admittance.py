"""Virtual admittance ``M dv/dt + B v = f_h`` (diagonal M, B), exact zero-order hold.

For a wrench held constant over one period ``T`` the exact solution per axis is::

    v[k+1] = a v[k] + (1 - a) f[k] / b,      a = exp(-b T / m)

which is stable and reaches the static gain ``1/b`` for any ``T`` (forward Euler is
unstable for ``T > 2 m / b``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from mmctl.config.control import AdmittanceConfig

Vec = NDArray[np.float64]


class Admittance:
    """Per-axis ZOH admittance: twist (6,) [m/s, rad/s] from wrench (6,) [N, N m].

    mass: (6,) M diagonal [kg | kg m^2]; damping: (6,) B diagonal [N s/m | N m s/rad].
    Stateless: :meth:`step` returns the next velocity; the caller keeps it.
    """

    def __init__(self, mass: Vec, damping: Vec) -> None:
        self.mass = np.asarray(mass, dtype=float).copy()
        self.damping = np.asarray(damping, dtype=float).copy()
        if self.mass.shape != (6,) or self.damping.shape != (6,):
            raise ValueError("mass and damping must have shape (6,)")
        if np.any(self.mass <= 0) or np.any(self.damping <= 0):
            raise ValueError("mass and damping must be > 0 on every axis")
        self._dt = -1.0
        self._a = np.zeros(6)
        self._g = np.zeros(6)

    @classmethod
    def from_config(cls, cfg: AdmittanceConfig) -> Admittance:
        return cls(np.array(cfg.mass), np.array(cfg.damping))

    def coefficients(self, dt: float) -> tuple[Vec, Vec]:
        """``(a, g)`` with ``v[k+1] = a v[k] + g f[k]`` for period ``dt`` [s] (cached)."""
        if dt != self._dt:
            a = np.exp(-self.damping * dt / self.mass)
            self._a, self._g, self._dt = a, (1.0 - a) / self.damping, dt
        return self._a, self._g

    def step(self, v: Vec, f: Vec, dt: float) -> Vec:
        """The velocity (6,) after ``dt`` [s] with wrench ``f`` (6,) held constant."""
        a, g = self.coefficients(dt)
        return a * v + g * f

    def time_constant(self) -> Vec:
        """Per-axis time constant m / b [s]."""
        tau: Vec = self.mass / self.damping
        return tau
