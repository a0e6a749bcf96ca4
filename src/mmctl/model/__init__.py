"""The robot model (Pinocchio): UR10e on a planar mecanum base; FK, Jacobian, inertia."""

from mmctl.model.robot import FRAMES, NA, NQ, Kinematics, RobotModel, base_jacobian, planar_pose

__all__ = ["FRAMES", "NA", "NQ", "Kinematics", "RobotModel", "base_jacobian", "planar_pose"]
