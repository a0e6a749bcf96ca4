"""The whole-body model against the UR DH table, finite differences and mechanics."""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
import pytest

from mmctl.config import config_from_dict, default_config
from mmctl.errors import ModelError
from mmctl.model import RobotModel, planar_pose
from mmctl.model.ur10e import MASSES, dh_forward


@pytest.fixture(scope="module")
def model() -> RobotModel:
    return RobotModel(default_config().robot)


def _random_q(rng: np.random.Generator) -> np.ndarray:
    return np.concatenate((rng.uniform(-math.pi, math.pi, 6), rng.uniform(-3, 3, 2),
                           rng.uniform(-math.pi, math.pi, 1)))


def test_flange_matches_dh_table_over_1000_configurations(model: RobotModel) -> None:
    rng = np.random.default_rng(1)
    mount = model._mount  # DH frame 0 in the base frame
    worst = 0.0
    for _ in range(1000):
        q = rng.uniform(-2 * math.pi, 2 * math.pi, 6)
        ours = mount.inverse() * model.fk_base(q, "flange")
        ref = dh_forward(q)
        worst = max(worst, float(np.abs(ours.translation - ref[:3, 3]).max()))
        assert np.allclose(ours.rotation, ref[:3, :3], atol=1e-12)
    assert worst < 1e-9


def test_world_fk_composes_base_pose(model: RobotModel) -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        q = _random_q(rng)
        expect = planar_pose(q[6], q[7], q[8]) * model.fk_base(q[:6])
        assert np.allclose(model.position(q), expect.translation, atol=1e-12)
        assert np.allclose(model.update(q).p, expect.translation, atol=1e-12)


def test_tool_and_sensor_offsets_follow_the_flange(model: RobotModel) -> None:
    cfg = default_config().robot
    q = model.q_des[:6]
    flange = model.fk_base(q, "flange")
    assert np.allclose(model.fk_base(q, "tool").translation,
                       flange.act(np.array(cfg.tool_offset)), atol=1e-12)
    assert np.allclose(model.fk_base(q, "sensor").translation,
                       flange.act(np.array(cfg.sensor_offset)), atol=1e-12)
    with pytest.raises(ModelError, match="frames: flange, sensor, tool"):
        model.fk_base(q, "gripper")


def test_q_des_puts_the_handle_in_front_at_elbow_height(model: RobotModel) -> None:
    p = model.update(model.q_des).p_base
    assert 0.3 < p[0] < 0.8 and 0.8 < p[2] < 1.3


def _world_pose(model: RobotModel, q: np.ndarray) -> pin.SE3:
    return model.fk(q)


def _integrate(q: np.ndarray, qdot: np.ndarray, h: float) -> np.ndarray:
    """Move q by qdot for h seconds (base twist in the base frame, exact for a short step)."""
    out = q + h * qdot
    c, s = math.cos(q[8] + 0.5 * h * qdot[8]), math.sin(q[8] + 0.5 * h * qdot[8])
    out[6] = q[6] + h * (c * qdot[6] - s * qdot[7])
    out[7] = q[7] + h * (s * qdot[6] + c * qdot[7])
    return out


def test_jacobian_matches_finite_differences(model: RobotModel) -> None:
    rng = np.random.default_rng(3)
    h = 1e-6
    for _ in range(100):
        q = _random_q(rng)
        J = model.jacobian(q)
        R_wb = planar_pose(q[6], q[7], q[8]).rotation
        for k in range(9):
            e = np.zeros(9)
            e[k] = 1.0
            plus, minus = model.fk(_integrate(q, e, h)), model.fk(_integrate(q, e, -h))
            v_world = (plus.translation - minus.translation) / (2 * h)
            w_world = pin.log3(plus.rotation @ minus.rotation.T) / (2 * h)
            assert np.allclose(R_wb.T @ v_world, J[:3, k], atol=1e-6), k
            assert np.allclose(R_wb.T @ w_world, J[3:, k], atol=1e-6), k


def test_arm_inertia_is_symmetric_positive_definite(model: RobotModel) -> None:
    rng = np.random.default_rng(4)
    for _ in range(200):
        q = _random_q(rng)
        Ma = model.arm_inertia(q[:6])
        assert np.allclose(Ma, Ma.T, atol=1e-12)
        assert np.linalg.eigvalsh(Ma)[0] > 0.0
        M = model.block_inertia(q[:6])
        assert np.allclose(M[6:, 6:], np.diag([115.0, 115.0, 15.0]))
        assert np.all(M[:6, 6:] == 0.0)


def test_arm_kinetic_energy_matches_link_velocities(model: RobotModel) -> None:
    """0.5 qd' M_a qd equals the sum of the links' kinetic energies from their twists."""
    rng = np.random.default_rng(5)
    arm, data = model.arm, model.arm_data
    for _ in range(20):
        q, qd = rng.uniform(-3, 3, 6), rng.normal(size=6)
        pin.forwardKinematics(arm, data, q, qd)
        e_links = sum(
            0.5 * data.v[j].vector @ arm.inertias[j].matrix() @ data.v[j].vector
            for j in range(1, arm.njoints)
        )
        assert qd @ model.arm_inertia(q) @ qd / 2 == pytest.approx(e_links, rel=1e-10)
    assert sum(i.mass for i in arm.inertias) == pytest.approx(sum(MASSES))


def test_coupled_inertia_blocks(model: RobotModel) -> None:
    rng = np.random.default_rng(6)
    for _ in range(20):
        q = _random_q(rng)
        Mf = model.coupled_inertia(q[:6])
        assert np.allclose(Mf, Mf.T, atol=1e-10)
        assert np.allclose(Mf[:6, :6], model.arm_inertia(q[:6]), atol=1e-12)
        total = 115.0 + sum(MASSES)
        assert Mf[6, 6] == pytest.approx(total) and Mf[7, 7] == pytest.approx(total)
        assert Mf[8, 8] > 15.0
        # a pure base translation moves every arm link with the base: E = m_total v^2 / 2
        qd = np.zeros(9)
        qd[6] = 0.5
        assert qd @ Mf @ qd / 2 == pytest.approx(total * 0.25 / 2)


def test_full_inertia_flag_selects_the_matrix() -> None:
    cfg = config_from_dict({"robot": {"full_inertia": True}})
    m = RobotModel(cfg.robot)
    q = m.q_des
    k = m.update(q)
    assert k.M_full is not None and np.allclose(k.M_full, m.coupled_inertia(q[:6]))
    assert np.allclose(m.inertia(q[:6]), k.M_full)
