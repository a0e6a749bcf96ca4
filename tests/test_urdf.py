"""The robot's body (model/geometry.py) and its URDF (model/urdf.py, `mmctl model`)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

from mmctl.cli import main
from mmctl.config import Config, load_config
from mmctl.errors import ConfigError
from mmctl.model.geometry import PAIRS, BodyModel, body_shapes
from mmctl.model.robot import RobotModel
from mmctl.model.ur10e import JOINT_NAMES
from mmctl.model.urdf import urdf

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def cfg() -> Config:
    return load_config(ROOT / "config" / "sim.yaml")


def _random_q(rng: np.random.Generator) -> np.ndarray:
    return np.r_[rng.uniform(-2 * np.pi, 2 * np.pi, 6), rng.uniform(-20, 20, 2),
                 rng.uniform(-np.pi, np.pi)]


@pytest.mark.parametrize("base", ["fixed", "planar"])
def test_the_urdfs_forward_kinematics_are_the_models_at_1000_random_poses(cfg: Config,
                                                                           base: str) -> None:
    model = RobotModel(cfg.robot)
    robot = pin.buildModelFromXML(urdf(cfg, base))
    data = robot.createData()
    assert robot.nq == (6 if base == "fixed" else 10)
    frames = {"handle": "tool", "sensor": "sensor", "flange": "flange"}
    ids = {ours: robot.getFrameId(theirs) for theirs, ours in frames.items()}
    rng = np.random.default_rng(29)
    worst = 0.0
    for _ in range(1000):
        q = _random_q(rng)
        if base == "fixed":
            q_urdf = q[:6]
        else:
            q_urdf = np.r_[q[6], q[7], np.cos(q[8]), np.sin(q[8]), q[:6]]
        pin.framesForwardKinematics(robot, data, q_urdf)
        for ours, fid in ids.items():
            want = model.fk(q, ours) if base == "planar" else model.fk_base(q, ours)
            worst = max(worst, float(np.abs(data.oMf[fid].homogeneous
                                             - want.homogeneous).max()))
    assert worst < 1e-9


def test_the_urdf_names_ur_descriptions_joints_with_the_configured_limits(cfg: Config) -> None:
    robot = pin.buildModelFromXML(urdf(cfg))
    names = [robot.names[i] for i in range(1, robot.njoints)]
    assert names == [f"{n}_joint" for n in JOINT_NAMES]
    assert names[0] == "shoulder_pan_joint" and names[-1] == "wrist_3_joint"
    np.testing.assert_allclose(robot.lowerPositionLimit, cfg.limits.joint_position_min)
    np.testing.assert_allclose(robot.upperPositionLimit, cfg.limits.joint_position_max)
    np.testing.assert_allclose(robot.velocityLimit, cfg.limits.joint_velocity)
    # the arm's inertias are the model's: the whole mass, and the joint-space inertia
    model = RobotModel(cfg.robot)
    assert sum(i.mass for i in robot.inertias) == pytest.approx(
        model.arm_mass + cfg.robot.base_mass, abs=1e-9)
    q = np.array([0.3, -1.2, 1.4, -0.7, 1.1, 0.2])
    np.testing.assert_allclose(pin.crba(robot, robot.createData(), q), model.arm_inertia(q),
                               atol=1e-9)


def _urdf_component_owner(cfg: Config) -> list[str]:
    """The shape each of the URDF's collision objects belongs to, in pinocchio's order
    (per link in file order; a capsule is three objects: cylinder, two spheres)."""
    from mmctl.model.urdf import link_name

    model = RobotModel(cfg.robot)
    shapes = body_shapes(cfg.robot, model.mount)
    links = ["base_link"] + [link_name(j) for j in range(1, 7)]
    owners = []
    for lname in links:
        for s in shapes:
            if link_name(s.joint) == lname:
                owners += [s.name] * (3 if s.kind == "capsule" else 1)
    return owners


def test_the_urdfs_collision_shapes_are_the_checked_ones(cfg: Config) -> None:
    """A capsule written as a cylinder and two spheres is the same solid: every checked
    pair's distance from the URDF's own geometry equals the body model's."""
    text = urdf(cfg)
    robot = pin.buildModelFromXML(text)
    geom = pin.buildGeomFromUrdfString(robot, text, pin.GeometryType.COLLISION)
    owners = _urdf_component_owner(cfg)
    assert len(owners) == len(geom.geometryObjects)
    parts: dict[str, list[int]] = {}
    for i, name in enumerate(owners):
        parts.setdefault(name, []).append(i)
    for a, b in PAIRS:
        for i in parts.get(a, []):
            for j in parts.get(b, []):
                geom.addCollisionPair(pin.CollisionPair(i, j))
    gdata = pin.GeometryData(geom)
    model = RobotModel(cfg.robot)
    body = BodyModel(cfg.robot, model.arm, model.mount)
    rng = np.random.default_rng(7)
    for _ in range(100):
        q = rng.uniform(-np.pi, np.pi, 6)
        pin.computeDistances(robot, robot.createData(), geom, gdata, q)
        from_urdf: dict[tuple[str, str], float] = {}
        for pair, res in zip(geom.collisionPairs, gdata.distanceResults):
            key = (owners[pair.first], owners[pair.second])
            from_urdf[key] = min(from_urdf.get(key, np.inf), res.min_distance)
        for d in body.distances(q):
            if d.distance > 0:  # (overlap depths of unions and of capsules differ)
                # (1e-5: coal solves a cylinder by GJK to its own tolerance)
                assert from_urdf[d.pair] == pytest.approx(d.distance, abs=1e-5), d.pair


def test_the_body_is_clear_of_itself_at_the_preferred_pose_and_meets_where_expected(
        cfg: Config) -> None:
    model = RobotModel(cfg.robot)
    body = BodyModel(cfg.robot, model.arm, model.mount)
    q_des = np.asarray(cfg.robot.q_des)
    assert body.closest(q_des).distance > 0.05  # the default collision margin
    # the deck and the handle, by hand: with the handle's two ends above the deck, their
    # distance is the lower end's height less the radius and the deck's height
    rng = np.random.default_rng(3)
    checked = 0
    deck_top = cfg.robot.deck_size[2]
    half = np.asarray(cfg.robot.deck_size[:2]) / 2
    while checked < 20:
        q = np.r_[rng.uniform(-np.pi, np.pi, 6), 0.0, 0.0, 0.0]
        ends = [model.fk_base(q, "sensor").translation, model.fk_base(q, "tool").translation]
        low = min(ends, key=lambda p: p[2])
        if not all(np.all(np.abs(p[:2]) < half - 0.1) for p in ends) or low[2] < deck_top:
            continue
        d = {x.pair: x.distance for x in body.distances(q[:6])}[("deck", "handle")]
        # (the sensor frame is the handle's lower end: sensor_rotation is zero here)
        assert d == pytest.approx(low[2] - cfg.robot.handle_radius - deck_top, abs=1e-6)
        checked += 1
    # folded onto itself, the wrist is inside the upper arm: a negative distance
    folded = np.array([0.0, -1.57, 3.1, -1.4, 1.57, 0.0])
    d = {x.pair: x.distance for x in body.distances(folded)}
    assert min(d[("upper_arm", "wrist_1")], d[("upper_arm", "wrist_2")],
               d[("upper_arm", "wrist_3")], d[("upper_arm", "sensor")],
               d[("upper_arm", "handle")]) < 0.0


def test_a_cabinet_is_checked_only_when_it_has_a_size(cfg: Config) -> None:
    model = RobotModel(cfg.robot)
    assert not any("cabinet" in p for p in BodyModel(cfg.robot, model.arm, model.mount).pairs)
    robot = dataclasses.replace(cfg.robot, cabinet_size=(0.3, 0.3, 1.2),
                                cabinet_center=(-0.3, 0.0, 1.16))
    pairs = BodyModel(robot, model.arm, model.mount).pairs
    assert ("cabinet", "handle") in pairs and ("cabinet", "upper_arm") in pairs


def test_a_deck_taller_than_the_arms_mount_is_refused_by_name(tmp_path: Path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("robot:\n  deck_size: [0.9, 0.7, 0.8]\n", encoding="utf-8")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert "robot.deck_size" in str(err.value) and "arm_mount" in str(err.value)


def test_mmctl_model_writes_the_urdf_and_prints_the_distances(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "robot.urdf"
    assert main(["model", "urdf", "--base", "planar", "--output", str(out)]) == 0
    robot = pin.buildModelFromXML(out.read_text(encoding="utf-8"))
    assert robot.names[1] == "base_x_joint" and robot.nq == 10
    assert main(["model", "distances", "--q", "0", "-1.57", "3.1", "-1.4", "1.57", "0"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split()[0] == "pair"
    first = lines[1].split()
    assert float(first[-1]) < 0.0  # sorted: the overlapping pair first
