"""The whole robot as a URDF: the model's kinematics, inertias and collision shapes.

Written from the same numbers the controller uses (:class:`~mmctl.model.robot.RobotModel`
and :func:`~mmctl.model.geometry.body_shapes`), so its forward kinematics equal the
model's (``tests/test_urdf.py``: 1e-9 at 1 000 random poses).

* The root is ``base_link`` (the mobile base, at floor height), as ROS expects when
  odometry publishes ``odom -> base_link``; ``base="planar"`` adds ``odom`` and the
  base's three joints (``base_x_joint``, ``base_y_joint`` prismatic, ``base_yaw_joint``
  continuous) for tools that want the whole body as one chain.
* The UR10e's joints and links carry ur_description's names (``shoulder_pan_joint`` ...
  ``wrist_3_joint``, ``shoulder_link`` ... ``wrist_3_link``), its base is ``ur_base``,
  and the frames after the wrist are ``flange`` (UR's ``tool0``), ``sensor`` (the F/T
  measurement frame) and ``handle`` (the controlled point, the model's ``tool``).
* Joint limits are the configured ``limits:`` (position and speed) and the UR10e's
  rated torques.
* Each collision shape is written in URDF's own primitives (a capsule as a cylinder and
  a sphere at each end: the same solid), once as ``collision`` and once as ``visual``.
"""

from __future__ import annotations

import math
from xml.sax.saxutils import quoteattr

import numpy as np
import pinocchio as pin

from mmctl.config import Config
from mmctl.model.geometry import ARM_LINKS, Shape, body_shapes, length, placement
from mmctl.model.robot import RobotModel, sensor_rotation
from mmctl.model.ur10e import JOINT_NAMES, dh_transform, link_inertia

#: the UR10e's rated joint torques [N m] (sizes 4, 4, 3, 2, 2, 2)
UR10E_EFFORT = (330.0, 330.0, 150.0, 56.0, 56.0, 56.0)
BASE_CHOICES = ("fixed", "planar")
_COLOURS = {"deck": "0.35 0.35 0.4 1", "cabinet": "0.35 0.35 0.4 1",
            "sensor": "0.2 0.2 0.2 1", "handle": "0.9 0.5 0.1 1"}
_ARM_COLOUR = "0.7 0.7 0.7 1"


def _num(x: float) -> str:
    return repr(float(x))


def _origin(m: pin.SE3) -> str:
    xyz = " ".join(_num(v) for v in m.translation)
    rpy = " ".join(_num(v) for v in pin.rpy.matrixToRpy(m.rotation))
    return f'<origin xyz="{xyz}" rpy="{rpy}"/>'


def link_name(joint: int) -> str:
    """The URDF link that moves with the model's joint ``joint`` (0: base_link)."""
    return "base_link" if joint == 0 else f"{ARM_LINKS[joint - 1]}_link"


def _shape_xml(s: Shape) -> list[tuple[str, str]]:
    """The shape as URDF geometry elements: (a name unique in the robot, origin and
    geometry); a capsule's end spheres are ``NAME_end_a`` and ``NAME_end_b`` (viewers
    such as rerun's file one entity per name)."""
    frame = placement(s)
    if s.kind == "box":
        size = " ".join(_num(v) for v in s.b)
        return [(s.name, f'{_origin(frame)}<geometry><box size="{size}"/></geometry>')]
    cylinder = (f'<cylinder radius="{_num(s.radius)}" '
                f'length="{_num(max(length(s), 1e-4))}"/>')
    out = [(s.name, f'{_origin(frame)}<geometry>{cylinder}</geometry>')]
    if s.kind == "capsule":
        for tag, end in (("a", s.a), ("b", s.b)):
            out.append((f"{s.name}_end_{tag}",
                        (f'{_origin(pin.SE3(np.eye(3), np.asarray(end)))}'
                        f'<geometry><sphere radius="{_num(s.radius)}"/></geometry>')))
    return out


def _inertial(mass: float, com: np.ndarray, frame: pin.SE3, tensor: np.ndarray) -> str:
    at = pin.SE3(frame.rotation, frame.act(com))
    t = tensor
    return (f'<inertial>{_origin(at)}<mass value="{_num(mass)}"/>'
            f'<inertia ixx="{_num(t[0, 0])}" ixy="{_num(t[0, 1])}" ixz="{_num(t[0, 2])}" '
            f'iyy="{_num(t[1, 1])}" iyz="{_num(t[1, 2])}" izz="{_num(t[2, 2])}"/></inertial>')


def arm_joint_origins() -> list[pin.SE3]:
    """The six arm joints' origins in their parent links (the URDF's ``<origin>``; the
    joint turns about its z after it): ``ur_base`` for the first, then each DH step's
    constant part."""
    return [pin.SE3.Identity()] + [dh_transform(i) for i in range(5)]


_ORIGIN_ROTATIONS = [o.rotation for o in arm_joint_origins()]


def arm_joint_quaternions(q_a: np.ndarray) -> np.ndarray:
    """(6, 4) (x, y, z, w): each arm joint's child link in its parent link at the arm's
    joints ``q_a`` (6,): the URDF's origin (:func:`arm_joint_origins`) times the turn
    about z."""
    out = np.empty((6, 4))
    for i, (origin, angle) in enumerate(zip(_ORIGIN_ROTATIONS, np.asarray(q_a).tolist())):
        c, s = math.cos(angle), math.sin(angle)
        rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        quat = pin.Quaternion(origin @ rz)
        out[i] = (quat.x, quat.y, quat.z, quat.w)
    return out


def fixed_joints(cfg: Config) -> list[tuple[str, str, str, pin.SE3]]:
    """The robot's fixed joints (name, parent link, child link, origin): the arm's base
    on the mobile base, then the flange, the sensor and the handle after the wrist."""
    robot = cfg.robot
    return [
        ("ur_base_joint", "base_link", "ur_base", RobotModel(robot).mount),
        ("flange_joint", "wrist_3_link", "flange", dh_transform(5)),
        ("sensor_joint", "flange", "sensor",
         pin.SE3(sensor_rotation(robot), np.asarray(robot.sensor_offset, dtype=float))),
        ("handle_joint", "flange", "handle",
         pin.SE3(np.eye(3), np.asarray(robot.tool_offset, dtype=float))),
    ]


def urdf(cfg: Config, base: str = "fixed", name: str = "mmctl_mobile_manipulator",
         collision: bool = True) -> str:
    """The robot of ``cfg`` as URDF text (see the module docstring); ``collision``
    False leaves out the ``<collision>`` elements (a viewer's copy: the same shapes as
    the visuals)."""
    if base not in BASE_CHOICES:
        raise ValueError(f"base must be one of {BASE_CHOICES}, not {base!r}")
    robot = cfg.robot
    model = RobotModel(robot)
    shapes = body_shapes(robot, model.mount)
    by_link: dict[str, list[Shape]] = {}
    for s in shapes:
        by_link.setdefault(link_name(s.joint), []).append(s)
    out = [f'<?xml version="1.0"?>\n<robot name={quoteattr(name)}>']
    for colour_name, rgba in (("arm", _ARM_COLOUR), *_COLOURS.items()):
        out.append(f'  <material name="{colour_name}"><color rgba="{rgba}"/></material>')

    def link(lname: str, inertial: str = "") -> None:
        body = [inertial] if inertial else []
        for s in by_link.get(lname, []):
            material = s.name if s.name in _COLOURS else "arm"
            for gname, geom in _shape_xml(s):
                body.append(f'<visual name={quoteattr(gname)}>{geom}'
                            f'<material name="{material}"/></visual>')
                if collision:
                    body.append(f'<collision name={quoteattr(gname)}>{geom}</collision>')
        inner = "\n    ".join(body)
        out.append(f'  <link name="{lname}">\n    {inner}\n  </link>' if body
                   else f'  <link name="{lname}"/>')

    def joint(jname: str, kind: str, parent: str, child: str, origin: pin.SE3,
              axis: str = "0 0 1", limit: str = "") -> None:
        parts = [f'<parent link="{parent}"/>', f'<child link="{child}"/>', _origin(origin)]
        if kind != "fixed":
            parts.append(f'<axis xyz="{axis}"/>')
        if limit:
            parts.append(limit)
        inner = "".join(parts)
        out.append(f'  <joint name="{jname}" type="{kind}">{inner}</joint>')

    ident = pin.SE3.Identity()
    if base == "planar":
        link("odom")
        link("base_x")
        link("base_y")
        joint("base_x_joint", "prismatic", "odom", "base_x", ident, "1 0 0",
              '<limit lower="-1000" upper="1000" effort="10000" velocity="3"/>')
        joint("base_y_joint", "prismatic", "base_x", "base_y", ident, "0 1 0",
              '<limit lower="-1000" upper="1000" effort="10000" velocity="3"/>')
        joint("base_yaw_joint", "continuous", "base_y", "base_link", ident, "0 0 1",
              '<limit effort="10000" velocity="3"/>')
    i_bz = robot.base_inertia_z
    link("base_link", _inertial(robot.base_mass, np.zeros(3), ident,
                                np.diag([i_bz, i_bz, i_bz])))
    link("ur_base")
    joint("ur_base_joint", "fixed", "base_link", "ur_base", model.mount)
    lim = cfg.limits
    parent = "ur_base"
    origins = arm_joint_origins()
    for i in range(6):
        child = link_name(i + 1)
        dh = dh_transform(i)
        inertia = link_inertia(i)
        link(child, _inertial(inertia.mass, inertia.lever, dh, inertia.inertia))
        origin = origins[i]
        limit = (f'<limit lower="{_num(lim.joint_position_min[i])}" '
                 f'upper="{_num(lim.joint_position_max[i])}" '
                 f'effort="{_num(UR10E_EFFORT[i])}" velocity="{_num(lim.joint_velocity[i])}"/>')
        joint(f"{JOINT_NAMES[i]}_joint", "revolute", parent, child, origin, limit=limit)
        parent = child
    for jname, jparent, jchild, origin in fixed_joints(cfg)[1:]:
        link(jchild)
        joint(jname, "fixed", jparent, jchild, origin)
    out.append("</robot>\n")
    return "\n".join(out)
