"""UR10e kinematic and inertial parameters, and the Pinocchio arm chain built from them.

Source: Universal Robots' published DH table and dynamics table for the UR10e (the
copy in ``reference/ur10e/``).  The reference YAML stores the centres of mass in the
ROS ``ur_description`` link frames; its comments give the conversion from UR's
DH-frame values (``model.x`` ...).  We invert that conversion and work in the
standard DH frames throughout:

* frame ``i`` (i = 1..6) is attached to link ``i`` and obtained from frame ``i-1`` by
  ``Rz(theta_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``; frame 0 is the arm base, frame 6 the
  tool flange (UR's ``tool0``: z out of the flange);
* ``COM_DH[i]`` is link ``i+1``'s centre of mass in DH frame ``i+1`` [m];
* ``INERTIA_DH[i]`` is its inertia tensor about the centre of mass, with the axes of
  DH frame ``i+1`` [kg m^2] (the YAML's ``rotation`` entries map exactly these axes
  to the ROS link frames, so the tensors need no rotation here).
"""

from __future__ import annotations

import math

import numpy as np
import pinocchio as pin
from numpy.typing import NDArray

Mat = NDArray[np.float64]

#: DH parameters (standard convention), metres and radians.
DH_D = (0.1807, 0.0, 0.0, 0.17415, 0.11985, 0.11655)
DH_A = (0.0, -0.6127, -0.57155, 0.0, 0.0, 0.0)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)

#: Link masses [kg] (shoulder, upper arm, forearm, wrist 1, wrist 2, wrist 3).
MASSES = (7.369, 13.051, 3.989, 2.1, 1.98, 0.615)

#: Centres of mass in their DH frames [m] (UR's table; YAML value converted back).
COM_DH = (
    (0.021, 0.0, 0.027),  # YAML (0.021, -0.027, 0.0) = (x, -z, y)
    (0.38, 0.0, 0.158),  # YAML x -0.2327 = model.x - 0.6127
    (0.24, 0.0, 0.068),  # YAML x -0.33155 = model.x - 0.57155
    (0.0, 0.007, 0.018),  # YAML (0, -0.018, 0.007) = (x, -z, y)
    (0.0, 0.007, 0.018),  # YAML (0, 0.018, -0.007) = (x, z, -y)
    (0.0, 0.0, -0.026),
)

#: Inertia tensors about the COM, DH-frame axes [kg m^2]: (ixx, ixy, ixz, iyy, iyz, izz).
INERTIA_DH = (
    (0.03408, 0.00002, -0.00425, 0.03529, 0.00008, 0.02156),
    (0.02814, 0.00005, -0.01561, 0.77068, 0.00002, 0.76943),
    (0.01014, 0.00008, 0.00916, 0.30928, 0.0, 0.30646),
    (0.00296, -0.00001, 0.0, 0.00222, -0.00024, 0.00258),
    (0.00296, -0.00001, 0.0, 0.00222, -0.00024, 0.00258),
    (0.00040, 0.0, 0.0, 0.00041, 0.0, 0.00034),
)

JOINT_NAMES = (
    "shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3",
)


def dh_transform(i: int) -> pin.SE3:
    """The constant part ``Tz(d_i) Tx(a_i) Rx(alpha_i)`` of DH step ``i`` (0-based)."""
    ca, sa = math.cos(DH_ALPHA[i]), math.sin(DH_ALPHA[i])
    rot = np.array([[1.0, 0.0, 0.0], [0.0, ca, -sa], [0.0, sa, ca]])
    return pin.SE3(rot, np.array([DH_A[i], 0.0, DH_D[i]]))


def link_inertia(i: int) -> pin.Inertia:
    """Spatial inertia of link ``i`` (0-based) in its own DH frame."""
    ixx, ixy, ixz, iyy, iyz, izz = INERTIA_DH[i]
    tensor = np.array([[ixx, ixy, ixz], [ixy, iyy, iyz], [ixz, iyz, izz]])
    return pin.Inertia(MASSES[i], np.array(COM_DH[i]), tensor)


def add_arm(model: pin.Model, parent: int, mount: pin.SE3) -> tuple[int, ...]:
    """Append the six revolute UR10e joints and links under joint ``parent``.

    ``mount`` places DH frame 0 in the parent joint frame.  Joint ``i`` rotates about
    the z axis of DH frame ``i-1``; link ``i`` (DH frame ``i``) hangs from it.
    Returns the six joint ids.  Adds the frame ``"flange"`` (DH frame 6).
    """
    ids = []
    placement = mount
    for i in range(6):
        jid = model.addJoint(
            parent, pin.JointModelRZ(), placement, JOINT_NAMES[i],
            np.array([10.0]), np.array([math.pi]), np.array([-2 * math.pi]),
            np.array([2 * math.pi]),
        )
        dh = dh_transform(i)
        model.appendBodyToJoint(jid, link_inertia(i), dh)
        model.addFrame(pin.Frame(f"link{i + 1}", jid, dh, pin.FrameType.BODY))
        ids.append(jid)
        parent = jid
        placement = dh
    model.addFrame(
        pin.Frame("flange", ids[-1], dh_transform(5), pin.FrameType.OP_FRAME)
    )
    return tuple(ids)


def dh_forward(q: Mat) -> Mat:
    """Flange pose (4x4) in DH frame 0 by the plain DH product (a reference for tests)."""
    t = np.eye(4)
    for i in range(6):
        ct, st = math.cos(q[i]), math.sin(q[i])
        ca, sa = math.cos(DH_ALPHA[i]), math.sin(DH_ALPHA[i])
        t = t @ np.array(
            [
                [ct, -st * ca, st * sa, DH_A[i] * ct],
                [st, ct * ca, -ct * sa, DH_A[i] * st],
                [0.0, sa, ca, DH_D[i]],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
    return t
