"""The robot's body: collision shapes of the UR10e, the sensor, the handle and the base.

One description (:func:`body_shapes`) feeds Pinocchio's ``GeometryModel`` (distances by
coal, the FCL successor Pinocchio's wheel brings: no distance code of our own) and the
URDF (:mod:`mmctl.model.urdf`).  Every shape hangs from a joint of
:attr:`mmctl.model.robot.RobotModel.arm` (0: ``base_link``, 1-6: the UR joints), placed
in that joint's frame (the frame that turns with the joint: origin on the joint's
axis at DH frame ``i - 1``'s origin, z the joint's axis).

Sizes (docs/hand-guiding.md, "The robot's body", gives the derivation):

* the UR10e's links are capsules along the DH lines, shifted along the joint axes where
  UR's own meshes sit (ur_description ``config/ur10e/visual_parameters.yaml``: the upper
  arm 0.1762 m, the forearm 0.0393 m), with the radii of ``robot.link_radii`` (default:
  the largest cross-section of ur_description's ``meshes/ur10e/collision/*.stl``);
* the arm's base is a cylinder of 95 mm radius and 99.3 mm height (the base mesh);
* the F/T sensor is a cylinder from the flange to the sensor frame
  (``robot.sensor_radius``, ``robot.sensor_offset``), the handle a capsule from there to
  the handle point (``robot.handle_radius``, ``robot.tool_offset``);
* the base's deck is a box from the floor up (``robot.deck_size``, ``robot.deck_center``),
  and an optional cabinet or mast another (``robot.cabinet_size``).

:data:`PAIRS` lists the pairs that can meet; adjacent links, and shapes that overlap at
every pose (the shoulder on the deck), are not checked.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pinocchio as pin

from mmctl.config.robot import RobotConfig
from mmctl.model.ur10e import DH_A, DH_D, dh_transform

#: the upper arm's and the forearm's tubes along their joint axes, from the DH line
#: [m] (ur_description's mesh offsets for the UR10e)
UPPER_ARM_OFFSET = 0.1762
FOREARM_OFFSET = 0.0393
#: the arm's base (UR's base mesh): radius and height [m]
ARM_BASE_RADIUS = 0.095
ARM_BASE_HEIGHT = 0.0993
#: the wrist 1 housing along its joint axis, and the wrist 3 housing along its own
#: [m] (ur_description's wrist meshes: 0.106-0.221 m and 0.068-0.117 m along the axis,
#: less the capsule's radius at each end)
WRIST_1_SPAN = (0.153, 0.174)
WRIST_3_SPAN = (0.070, 0.095)
#: the shoulder's housing from the top of the arm's base up to the joint 2 axis [m]
SHOULDER_FROM = 0.10


class Shape(NamedTuple):
    """One collision shape.  ``kind``: ``capsule`` (segment ``a``-``b``, ``radius``),
    ``cylinder`` (axis from ``a`` to ``b``, ``radius``) or ``box`` (centre ``a``, full
    sizes ``b``, the joint frame's axes).  Points in the frame of joint ``joint``."""

    name: str
    joint: int
    kind: str
    a: tuple[float, float, float]
    b: tuple[float, float, float]
    radius: float = 0.0


#: the links of the arm, shoulder first (the URDF's link names are ur_description's)
ARM_LINKS = ("shoulder", "upper_arm", "forearm", "wrist_1", "wrist_2", "wrist_3")
_MOVING = (*ARM_LINKS[1:], "sensor", "handle")

#: the pairs that can meet, as names (cabinet pairs only when it exists)
PAIRS: tuple[tuple[str, str], ...] = (
    *(("deck", n) for n in _MOVING),
    *(("cabinet", n) for n in _MOVING),
    *(("arm_base", n) for n in ("forearm", "wrist_1", "wrist_2", "wrist_3", "sensor",
                                "handle")),
    *(("shoulder", n) for n in ("forearm", "wrist_1", "wrist_2", "wrist_3", "sensor",
                                "handle")),
    *(("upper_arm", n) for n in ("wrist_1", "wrist_2", "wrist_3", "sensor", "handle")),
    # (the forearm and wrist 3 are two joints apart inside the compact wrist: 9 cm at
    # the preferred pose and nearer in ordinary work; the tool folding back onto the
    # forearm is the sensor's and the handle's pairs)
    *(("forearm", n) for n in ("sensor", "handle")),
)


def _vec(*v: float) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


def _in(frame: pin.SE3, p: tuple[float, ...]) -> tuple[float, float, float]:
    q = frame.act(np.asarray(p, dtype=float))
    return _vec(*q)


def body_shapes(cfg: RobotConfig, mount: pin.SE3) -> list[Shape]:
    """The robot's collision shapes for ``cfg`` (``mount``: DH frame 0 in base_link)."""
    r = cfg.link_radii
    d1, d5 = DH_D[0], DH_D[4]
    a2, a3 = DH_A[1], DH_A[2]
    flange = dh_transform(5)  # the flange in joint 6's frame
    sensor_top = _in(flange, cfg.sensor_offset)
    shapes = [
        Shape("arm_base", 0, "cylinder", _in(mount, (0.0, 0.0, 0.0)),
              _in(mount, (0.0, 0.0, ARM_BASE_HEIGHT)), ARM_BASE_RADIUS),
        Shape("shoulder", 1, "capsule", _vec(0, 0, SHOULDER_FROM), _vec(0, 0, d1), r[0]),
        Shape("upper_arm", 2, "capsule", _vec(0, 0, UPPER_ARM_OFFSET),
              _vec(a2, 0, UPPER_ARM_OFFSET), r[1]),
        Shape("forearm", 3, "capsule", _vec(0, 0, FOREARM_OFFSET),
              _vec(a3, 0, FOREARM_OFFSET), r[2]),
        Shape("wrist_1", 4, "capsule", _vec(0, 0, WRIST_1_SPAN[0]),
              _vec(0, 0, WRIST_1_SPAN[1]), r[3]),
        Shape("wrist_2", 5, "capsule", _vec(0, 0, 0), _vec(0, 0, d5), r[4]),
        Shape("wrist_3", 6, "capsule", _vec(0, 0, WRIST_3_SPAN[0]),
              _vec(0, 0, WRIST_3_SPAN[1]), r[5]),
        Shape("sensor", 6, "cylinder", _in(flange, (0.0, 0.0, 0.0)), sensor_top,
              cfg.sensor_radius),
        Shape("handle", 6, "capsule", sensor_top, _in(flange, cfg.tool_offset),
              cfg.handle_radius),
    ]
    dx, dy, dz = cfg.deck_size
    cx, cy = cfg.deck_center
    shapes.append(Shape("deck", 0, "box", _vec(cx, cy, dz / 2), _vec(dx, dy, dz)))
    if min(cfg.cabinet_size) > 0.0:
        shapes.append(Shape("cabinet", 0, "box", _vec(*cfg.cabinet_center),
                            _vec(*cfg.cabinet_size)))
    return shapes


def placement(shape: Shape) -> pin.SE3:
    """The shape's own frame in its joint's frame: its centre, z along its axis (the
    segment's direction for a capsule or cylinder; the joint frame's axes for a box)."""
    a, b = np.asarray(shape.a), np.asarray(shape.b)
    if shape.kind == "box":
        return pin.SE3(np.eye(3), a)
    axis = b - a
    n = float(np.linalg.norm(axis))
    rot = np.eye(3) if n < 1e-12 else _z_to(axis / n)
    return pin.SE3(rot, (a + b) / 2)


def length(shape: Shape) -> float:
    """A capsule's or cylinder's length along its axis [m]."""
    return float(np.linalg.norm(np.subtract(shape.b, shape.a)))


def _z_to(u: np.ndarray) -> np.ndarray:
    """A rotation taking z to the unit vector ``u`` (the shortest turn)."""
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ u)
    if c > 1.0 - 1e-12:
        return np.eye(3)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(z, u)
    s = float(np.linalg.norm(v))
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    rot: np.ndarray = np.eye(3) + k + k @ k * ((1.0 - c) / (s * s))
    return rot


def coal_geometry(shape: Shape) -> object:
    """The shape as a coal collision geometry."""
    import coal

    if shape.kind == "box":
        return coal.Box(*shape.b)
    if shape.kind == "cylinder":
        return coal.Cylinder(shape.radius, max(length(shape), 1e-4))
    return coal.Capsule(shape.radius, length(shape))


def geometry_model(model: pin.Model, shapes: list[Shape]) -> pin.GeometryModel:
    """A ``GeometryModel`` of ``shapes`` on ``model``, with :data:`PAIRS` as its
    collision pairs (those whose shapes exist)."""
    geom = pin.GeometryModel()
    ids: dict[str, int] = {}
    for s in shapes:
        obj = pin.GeometryObject(s.name, s.joint, placement(s), coal_geometry(s))
        ids[s.name] = geom.addGeometryObject(obj)
    for a, b in PAIRS:
        if a in ids and b in ids:
            geom.addCollisionPair(pin.CollisionPair(ids[a], ids[b]))
    return geom


class Distance(NamedTuple):
    """One pair's distance [m] (negative: the shapes overlap by that much) and the
    nearest points on each, in base_link [m]."""

    pair: tuple[str, str]
    distance: float
    p1: tuple[float, float, float]
    p2: tuple[float, float, float]


class BodyModel:
    """Distances between the robot's own shapes at an arm configuration (its own
    Pinocchio data: one per thread)."""

    def __init__(self, cfg: RobotConfig, model: pin.Model, mount: pin.SE3) -> None:
        self.shapes = body_shapes(cfg, mount)
        self.model = model
        self.data = model.createData()
        self.geom = geometry_model(model, self.shapes)
        self.geom_data = pin.GeometryData(self.geom)
        names = [o.name for o in self.geom.geometryObjects]
        self.pairs = tuple((names[p.first], names[p.second])
                           for p in self.geom.collisionPairs)

    def distances(self, q_a: np.ndarray) -> list[Distance]:
        """Every pair's distance at arm joints ``q_a`` (6,) [rad]."""
        pin.computeDistances(self.model, self.data, self.geom, self.geom_data,
                             np.asarray(q_a[:6], dtype=float))
        out = []
        for pair, res in zip(self.pairs, self.geom_data.distanceResults):
            out.append(Distance(pair, float(res.min_distance),
                                _vec(*res.getNearestPoint1()), _vec(*res.getNearestPoint2())))
        return out

    def clearance(self, q_a: np.ndarray) -> float:
        """The distance of the nearest pair at ``q_a`` (6,) [m]."""
        pin.computeDistances(self.model, self.data, self.geom, self.geom_data,
                             np.asarray(q_a[:6], dtype=float))
        return float(min(r.min_distance for r in self.geom_data.distanceResults))

    def closest(self, q_a: np.ndarray) -> Distance:
        """The pair nearest to touching at ``q_a`` (6,) [rad]."""
        return min(self.distances(q_a), key=lambda d: d.distance)
