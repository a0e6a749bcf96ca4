"""The 3-D drawing of the robot for one sample, from forward kinematics (no rerun).

:class:`SceneBuilder` owns its own :class:`~mmctl.model.RobotModel` (Pinocchio data is
scratch space: one model per thread) and turns a
:class:`~mmctl.telemetry.sample.TelemetrySample` into a :class:`SceneFrame`: the base
pose in the odometry frame, the arm skeleton through the joint origins, the handle
frame, and the arrows and points drawn at the handle, all in the base frame.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

from mmctl.config.base import MecanumConfig
from mmctl.config.robot import RobotConfig
from mmctl.model import NA, RobotModel
from mmctl.model.urdf import arm_joint_quaternions
from mmctl.telemetry import layout
from mmctl.telemetry import ring as tr
from mmctl.telemetry.batch import base_frame
from mmctl.telemetry.sample import TelemetrySample

F64 = NDArray[np.float64]

#: height of the drawn base body [m] (floor to the top plate, below the arm mount)
BASE_BODY_HEIGHT = 0.45
#: margin drawn around the wheel centres for the base footprint [m]
FOOTPRINT_MARGIN = (0.13, 0.12)


class SceneFrame(NamedTuple):
    """One drawable frame.

    base_translation: (3,) base origin in the odometry frame [m];
    base_quaternion: (4,) base orientation (x, y, z, w) in the odometry frame;
    arm_points: (k, 3) polyline base -> arm mount -> joint origins -> flange -> handle,
    in the base frame [m]; handle_translation: (3,) [m] and handle_quaternion (4,)
    (x, y, z, w): the handle frame in the base frame; twist_vector, force_vector: (3,)
    arrows at the handle [m] (scaled by :data:`layout.TWIST_ARROW_SCALE`,
    :data:`layout.FORCE_ARROW_SCALE`); p_des: (3,) preferred position in the base frame [m];
    joint_quaternions: (6, 4) (x, y, z, w) each arm joint's child link in its parent
    (the URDF joint's origin, then the turn about its z: :data:`layout.ROBOT_JOINTS`).
    """

    base_translation: F64
    base_quaternion: F64
    arm_points: F64
    handle_translation: F64
    handle_quaternion: F64
    twist_vector: F64
    force_vector: F64
    p_des: F64
    joint_quaternions: F64


def yaw_quaternion(yaw: float) -> F64:
    """(x, y, z, w) of a rotation by ``yaw`` [rad] about z."""
    return np.array([0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw)])


def footprint_box(mecanum: MecanumConfig) -> tuple[F64, F64]:
    """(center (3,), half_size (3,)) of the base body box in the base frame [m]."""
    half = np.array([mecanum.half_length + FOOTPRINT_MARGIN[0],
                     mecanum.half_width + FOOTPRINT_MARGIN[1], 0.5 * BASE_BODY_HEIGHT])
    return np.array([0.0, 0.0, 0.5 * BASE_BODY_HEIGHT]), half


class SceneBuilder:
    """FK-based drawing of samples; one instance per thread (owns a model)."""

    def __init__(self, robot: RobotConfig):
        self.model = RobotModel(robot)
        self._data = self.model.arm.createData()
        self._tool = self.model.frame_id("tool")
        self._flange = self.model.frame_id("flange")
        self._mount = np.asarray(robot.arm_mount, dtype=float)

    def frame(self, s: TelemetrySample) -> SceneFrame:
        """Draw one sample (see :class:`SceneFrame`)."""
        arm, data = self.model.arm, self._data
        q_a = np.asarray(s.q_a, dtype=float)[:NA]
        pin.forwardKinematics(arm, data, q_a)
        flange = pin.updateFramePlacement(arm, data, self._flange)
        tool = pin.updateFramePlacement(arm, data, self._tool)
        pts = [np.array([0.0, 0.0, self._mount[2] - 0.1]), self._mount]
        pts += [data.oMi[j].translation for j in range(1, arm.njoints)]
        pts += [flange.translation, tool.translation]
        quat = pin.Quaternion(tool.rotation)
        x, y, yaw = (float(v) for v in s.base_pose[:3])
        f_h = np.asarray(s.f_h, dtype=float)
        v_d = np.asarray(s.v_d, dtype=float)
        return SceneFrame(
            base_translation=np.array([x, y, 0.0]),
            base_quaternion=yaw_quaternion(yaw),
            arm_points=np.array(pts),
            handle_translation=tool.translation.copy(),
            handle_quaternion=np.array([quat.x, quat.y, quat.z, quat.w]),
            twist_vector=v_d[:3] * layout.TWIST_ARROW_SCALE,
            force_vector=f_h[:3] * layout.FORCE_ARROW_SCALE,
            p_des=base_frame(tr.rows_of([s]), tr.P_DES)[0],  # as the plotted series
            joint_quaternions=arm_joint_quaternions(q_a),
        )
