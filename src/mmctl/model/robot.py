"""The whole-body model: UR10e on the planar RB-KAIROS+ base.

Generalised coordinates ``q`` (9,): six arm joints [rad], then the base pose
``(x, y, yaw)`` in the world (odometry) frame [m, m, rad].  Generalised velocities
``qdot`` (9,): six arm joint rates [rad/s], then the base twist ``(vx, vy, wz)``
expressed in the *base* frame [m/s, m/s, rad/s] (what the drives and odometry use).

Frames: ``world`` (odometry, z up), ``base`` (the mobile base's ``base_link`` at floor
height), ``arm_base`` (UR DH frame 0, at ``robot.arm_mount``), ``flange`` (UR tool0,
DH frame 6), ``sensor`` (F/T measurement frame) and ``tool`` (the handle point, the
controlled end-effector).  The sensor frame sits at ``robot.sensor_offset`` in the
flange frame, its axes turned by ``robot.sensor_rotation`` (:func:`sensor_rotation`);
the tool frame keeps the flange's axes.  The *control frame* is the base frame's axes
placed at the tool point: twists ``v = (v_lin [m/s], w [rad/s])`` and the Jacobian
use it.

The arm is a Pinocchio model built programmatically from UR's DH and dynamics tables
(:mod:`mmctl.model.ur10e`) whose root is the base frame; the base columns of the
Jacobian are closed form (a planar rigid motion).  For the full coupled inertia a
second model has a planar root joint (Pinocchio ``JointModelPlanar``, whose velocity
is expressed in the local = base frame, exactly our convention).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray
from scipy.linalg import lapack

from mmctl.config.robot import RobotConfig
from mmctl.errors import ModelError
from mmctl.model.ur10e import add_arm

Mat = NDArray[np.float64]

NQ = 9  #: size of q and qdot
NA = 6  #: arm joints
FRAMES = ("base", "arm_base", "flange", "sensor", "tool")

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_syev = lapack.dsyev
_EMPTY = np.zeros((0, 0))


class Kinematics(NamedTuple):
    """Everything one control cycle needs, evaluated at one configuration ``q``.

    J: (6, 9) tool twist in the control frame per unit qdot;
    M_a: (6, 6) arm joint-space inertia [kg m^2];
    M_b: (3,) diagonal of the base inertia (m_b, m_b, I_bz) [kg, kg, kg m^2];
    M_full: (9, 9) coupled whole-body inertia (arm, base order), or None when not asked;
    p_base: (3,) tool position in the base frame [m]; R_base: (3, 3) tool orientation
    in the base frame; p: (3,) tool position in the world frame [m].
    """

    J: Mat
    M_a: Mat
    M_b: Mat
    M_full: Mat | None
    p_base: Mat
    R_base: Mat
    p: Mat


def planar_pose(x: float, y: float, yaw: float) -> pin.SE3:
    """The base frame in the world for base coordinates (x, y [m], yaw [rad])."""
    c, s = math.cos(yaw), math.sin(yaw)
    return pin.SE3(np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]), np.array([x, y, 0.0]))


def sensor_rotation(cfg: RobotConfig) -> Mat:
    """R_flange_sensor (3, 3): the sensor's axes in the flange frame, from
    ``robot.sensor_rotation`` (roll, pitch, yaw [rad]: ``Rz(yaw) Ry(pitch) Rx(roll)``);
    the identity when the sensor's axes are the flange's."""
    roll, pitch, yaw = (float(a) for a in cfg.sensor_rotation)
    r: Mat = pin.rpy.rpyToMatrix(roll, pitch, yaw)
    return r


def tool_in_sensor(cfg: RobotConfig) -> Mat:
    """(3,) the handle point (``robot.tool_offset``) in the sensor frame [m]: where the
    person's force acts, as the sensor sees it (the lever of its torque)."""
    lever: Mat = sensor_rotation(cfg).T @ np.subtract(cfg.tool_offset, cfg.sensor_offset)
    return lever


def base_jacobian(p_base: Mat, out: Mat | None = None) -> Mat:
    """(6, 3) J_b: tool twist (control frame) per base twist (vx, vy, wz) (base frame).

    A planar rigid motion: v_lin = (vx - wz p_y, vy + wz p_x, 0), w = (0, 0, wz).
    """
    jb = np.zeros((6, 3)) if out is None else out
    jb[0, 0] = 1.0
    jb[1, 1] = 1.0
    jb[0, 2] = -p_base[1]
    jb[1, 2] = p_base[0]
    jb[5, 2] = 1.0
    return jb


class RobotModel:
    """Kinematics and inertia of the mobile manipulator (see the module docstring).

    Built once from :class:`RobotConfig`; methods take numpy arrays and return new
    arrays (the internal Pinocchio data is scratch space: one model per thread).
    """

    def __init__(self, cfg: RobotConfig) -> None:
        self.cfg = cfg
        mount = planar_pose(0.0, 0.0, cfg.arm_mount_yaw)
        mount.translation = np.asarray(cfg.arm_mount, dtype=float)
        self._mount = mount
        self.arm = pin.Model()
        self.arm.name = "ur10e_on_base"
        add_arm(self.arm, 0, mount)
        self._add_tool_frames(self.arm)
        self.arm_data = self.arm.createData()
        self.frame_ids = {n: self.arm.getFrameId(n) for n in ("flange", "sensor", "tool")}
        self._tool = self.frame_ids["tool"]
        self.M_b = np.array([cfg.base_mass, cfg.base_mass, cfg.base_inertia_z])
        self.q_des = np.concatenate((np.asarray(cfg.q_des, dtype=float), np.zeros(3)))
        self.arm_mass = float(sum(inertia.mass for inertia in self.arm.inertias))
        self.full_inertia = cfg.full_inertia
        self.whole: pin.Model | None = None
        self.whole_data: pin.Data | None = None
        self._q_whole = np.zeros(4 + NA)
        self._q_whole[2] = 1.0  # planar joint q = (x, y, cos, sin)
        self._J_template = np.zeros((6, NQ))
        self._J_template[:, NA:] = base_jacobian(np.zeros(3))

    @property
    def mount(self) -> pin.SE3:
        """The arm's base (UR DH frame 0) in base_link (``robot.arm_mount``, ``_yaw``)."""
        return self._mount

    # --- construction --------------------------------------------------------
    def _add_tool_frames(self, model: pin.Model) -> None:
        flange = model.getFrameId("flange")
        fl = model.frames[flange]
        for name, rot, offset in (("sensor", sensor_rotation(self.cfg), self.cfg.sensor_offset),
                                  ("tool", np.eye(3), self.cfg.tool_offset)):
            placement = fl.placement * pin.SE3(rot, np.asarray(offset, dtype=float))
            model.addFrame(pin.Frame(name, fl.parentJoint, placement, pin.FrameType.OP_FRAME))

    def _build_whole(self) -> None:
        """The coupled model: planar root joint carrying the base body, then the arm."""
        model = pin.Model()
        model.name = "mobile_manipulator"
        jid = model.addJoint(0, pin.JointModelPlanar(), pin.SE3.Identity(), "base")
        m_b, i_bz = self.cfg.base_mass, self.cfg.base_inertia_z
        # Only I_zz matters for a planar joint; x/y entries are any positive value.
        model.appendBodyToJoint(
            jid, pin.Inertia(m_b, np.zeros(3), np.diag([i_bz, i_bz, i_bz])), pin.SE3.Identity()
        )
        add_arm(model, jid, self._mount)
        self._add_tool_frames(model)
        self.whole = model
        self.whole_data = model.createData()

    # --- queries -------------------------------------------------------------
    def frame_id(self, name: str) -> int:
        """Pinocchio frame id in :attr:`arm` of a tool-side frame; lists the valid names."""
        if name not in self.frame_ids:
            raise ModelError(f"unknown frame {name!r}; frames: {', '.join(self.frame_ids)}")
        fid: int = self.frame_ids[name]
        return fid

    def fk_base(self, q_a: Mat, frame: str = "tool") -> pin.SE3:
        """Pose of ``frame`` in the base frame for arm joints ``q_a`` (6,) [rad]."""
        fid = self.frame_id(frame)
        pin.forwardKinematics(self.arm, self.arm_data, np.asarray(q_a[:NA], dtype=float))
        return pin.updateFramePlacement(self.arm, self.arm_data, fid).copy()

    def fk(self, q: Mat, frame: str = "tool") -> pin.SE3:
        """Pose of ``frame`` in the world frame for the whole-body ``q`` (9,)."""
        q = np.asarray(q, dtype=float)
        return planar_pose(q[6], q[7], q[8]) * self.fk_base(q, frame)

    def position(self, q: Mat, frame: str = "tool") -> Mat:
        """Position (3,) [m] of ``frame`` in the world frame."""
        p: Mat = self.fk(q, frame).translation.copy()
        return p

    def jacobian(self, q: Mat) -> Mat:
        """The (6, 9) whole-body Jacobian J = [J_a J_b] of the tool, control frame."""
        model, data = self.arm, self.arm_data
        pin.computeJointJacobians(model, data, np.asarray(q[:NA], dtype=float))
        x, y, _ = pin.updateFramePlacement(model, data, self._tool).translation.tolist()
        J = self._J_template.copy()  # base columns' constant entries preset
        J[:, :NA] = pin.getFrameJacobian(model, data, self._tool, _LWA)
        J[0, 8] = -y
        J[1, 8] = x
        return J

    def condition(self, q: Mat) -> float:
        """The condition number of J J^T at ``q`` (9,) (inf where it is singular): the
        controller's singularity measure (the Jacobian alone and LAPACK's ``syev``:
        the controller's singularity braking asks for it every cycle)."""
        jac = self.jacobian(q)
        w, _, info = _syev(jac.dot(jac.T), compute_v=0)
        if info != 0:  # as numpy.linalg.eigvalsh says it (a NaN in q)
            raise np.linalg.LinAlgError("Eigenvalues did not converge")
        lo, hi = w[0], w[-1]
        return float(hi / lo) if lo > 0.0 else math.inf

    def arm_inertia(self, q_a: Mat) -> Mat:
        """M_a(q_a) (6, 6) [kg m^2], UR10e joint-space inertia (CRBA)."""
        m: Mat = pin.crba(self.arm, self.arm_data, np.asarray(q_a[:NA], dtype=float)).copy()
        return m

    def block_inertia(self, q_a: Mat) -> Mat:
        """The paper's M(q_a) = blockdiag(M_a(q_a), M_b) (9, 9)."""
        m = np.zeros((NQ, NQ))
        m[:NA, :NA] = self.arm_inertia(q_a)
        m[NA:, NA:] = np.diag(self.M_b)
        return m

    def coupled_inertia(self, q_a: Mat) -> Mat:
        """The full coupled whole-body inertia (9, 9), order (arm, base), base velocities
        in the base frame.  Its base block includes the arm's mass (m_b + m_arm)."""
        if self.whole is None:
            self._build_whole()
        assert self.whole is not None and self.whole_data is not None
        self._q_whole[4:] = q_a[:NA]
        m = pin.crba(self.whole, self.whole_data, self._q_whole)
        order = [3, 4, 5, 6, 7, 8, 0, 1, 2]
        return np.ascontiguousarray(m[np.ix_(order, order)])

    def inertia(self, q_a: Mat) -> Mat:
        """M used by the controller: coupled if ``robot.full_inertia`` else block-diagonal."""
        return self.coupled_inertia(q_a) if self.full_inertia else self.block_inertia(q_a)

    def update(self, q: Mat, inertia: bool = True) -> Kinematics:
        """One pass at ``q`` (9,): tool pose, J (6, 9), M_a and (if configured) M_full."""
        q = np.asarray(q, dtype=float)
        q_a = q[:NA]
        model, data = self.arm, self.arm_data
        pin.computeJointJacobians(model, data, q_a)
        pose = pin.updateFramePlacement(model, data, self._tool)
        p_base = pose.translation.copy()  # own the data (the property is a view)
        x, y, z = p_base.tolist()
        J = self._J_template.copy()  # base columns' constant entries preset
        J[:, :NA] = pin.getFrameJacobian(model, data, self._tool, _LWA)
        J[0, 8] = -y
        J[1, 8] = x
        bx, by, yaw = q[NA:].tolist()
        c, s = math.cos(yaw), math.sin(yaw)
        p = np.array((bx + c * x - s * y, by + s * x + c * y, z))
        M_a = pin.crba(model, data, q_a) if inertia else _EMPTY
        M_full = self.coupled_inertia(q_a) if (inertia and self.full_inertia) else None
        return Kinematics(J, M_a, self.M_b, M_full, p_base, pose.rotation.copy(), p)
