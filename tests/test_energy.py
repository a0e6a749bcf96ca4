"""Kinetic energy of the whole body (paper eq. 10)."""

from __future__ import annotations

import numpy as np

from mmctl.config import default_config
from mmctl.control.energy import Energy, kinetic_energy, kinetic_energy_full
from mmctl.model import RobotModel


def test_block_energy_is_half_qdot_m_qdot_and_splits() -> None:
    model = RobotModel(default_config().robot)
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.uniform(-3, 3, 9)
        qd = rng.normal(size=9)
        k = model.update(q)
        e = kinetic_energy(k.M_a, k.M_b, qd)
        M = model.block_inertia(q[:6])
        assert np.isclose(e.total, 0.5 * qd @ M @ qd, rtol=1e-12)
        assert np.isclose(e.total, e.arm + e.base)
        assert np.isclose(e.base, 0.5 * (115 * qd[6] ** 2 + 115 * qd[7] ** 2 + 15 * qd[8] ** 2))
        assert np.isclose(kinetic_energy(k.M_a, np.diag(k.M_b), qd).total, e.total)
        assert np.isclose(kinetic_energy_full(M, qd), e.total)


def test_base_translation_energy_and_share() -> None:
    qd = np.zeros(9)
    qd[6] = 0.2  # 0.2 m/s forward, arm still
    e = kinetic_energy(np.eye(6), np.array([115.0, 115.0, 15.0]), qd)
    assert e == Energy(0.5 * 115 * 0.04, 0.0, 0.5 * 115 * 0.04)
    assert e.base_share() == 1.0
    assert Energy(0.0, 0.0, 0.0).base_share() == 0.0
