"""The ROS 2 bridge's publishing side: one telemetry row as ROS 2 messages on DDS.

Topics (each under ``ros2.topic_prefix`` when one is set):

======================== =================================== =================================
topic                    type                                what
======================== =================================== =================================
``/joint_states``        ``sensor_msgs/msg/JointState``      the UR joints (ur_description's
                                                             names): measured position, velocity
``/tf``                  ``tf2_msgs/msg/TFMessage``          ``odom -> base_link`` (odometry) and
                                                             the arm's six links
``/tf_static``           ``tf2_msgs/msg/TFMessage``          ``base_link -> ur_base``, ``wrist_3_link
                                                             -> flange -> sensor``, ``flange ->
                                                             handle`` (transient local)
``/robot_description``   ``std_msgs/msg/String``             the URDF (`mmctl model urdf`;
                                                             transient local)
``mmctl/wrench/raw``     ``geometry_msgs/msg/WrenchStamped`` the sensor's raw wrench, ``sensor``
``mmctl/wrench/human``   ``geometry_msgs/msg/WrenchStamped`` the human wrench f_h, ``handle`` frame
``mmctl/twist/desired``  ``geometry_msgs/msg/TwistStamped``  the admittance's twist v_d, ``handle``
``/diagnostics``         ``diagnostic_msgs/msg/DiagnosticArray`` state, mode, limit, E_K, the loop
======================== =================================== =================================

The stamps are the cycle's own time (its deadline, on the wall clock), so a subscriber
sees the sample's age.  Nothing is subscribed: the bridge never commands the robot.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pinocchio as pin

from mmctl.config import Config
from mmctl.model import NA, RobotModel
from mmctl.model.ur10e import JOINT_NAMES
from mmctl.model.urdf import arm_joint_origins, arm_joint_quaternions, fixed_joints, link_name, urdf
from mmctl.telemetry import ring as tr

#: the UR joints' names in ROS (ur_description)
ROS_JOINT_NAMES = tuple(f"{n}_joint" for n in JOINT_NAMES)
#: loopback only: discovery by unicast to 127.0.0.1 (no multicast leaves the machine);
#: a participant started later is found at the next announcement (every second)
LOCALHOST_XML = """<CycloneDDS xmlns="https://cdds.io/config"><Domain Id="any">
<General><Interfaces><NetworkInterface name="lo"/></Interfaces>
<AllowMulticast>false</AllowMulticast></General>
<Discovery><ParticipantIndex>auto</ParticipantIndex>
<MaxAutoParticipantIndex>32</MaxAutoParticipantIndex><SPDPInterval>1s</SPDPInterval>
<Peers><Peer address="127.0.0.1"/></Peers></Discovery></Domain></CycloneDDS>"""
SUBNET_XML = """<CycloneDDS xmlns="https://cdds.io/config"><Domain Id="any">
<Discovery><SPDPInterval>1s</SPDPInterval></Discovery></Domain></CycloneDDS>"""


def topic_name(prefix: str, name: str) -> str:
    """``name`` under the namespace ``prefix`` ('' = none): ``/robot1/joint_states``."""
    base = name if name.startswith("/") else "/" + name
    p = prefix.strip("/")
    return f"/{p}{base}" if p else base


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw))


def _quat(rot: np.ndarray) -> tuple[float, float, float, float]:
    q = pin.Quaternion(rot)
    return (q.x, q.y, q.z, q.w)


class Ros2Bridge:
    """The DDS participant and its writers for ``cfg`` (see the module docstring).

    origin_wall: the wall-clock time [s since the epoch] of the loop's origin (a row's
    ``t`` is its deadline since then)."""

    def __init__(self, cfg: Config, origin_wall: float = 0.0):
        from cyclonedds.core import Policy, Qos
        from cyclonedds.domain import Domain, DomainParticipant
        from cyclonedds.pub import DataWriter
        from cyclonedds.topic import Topic
        from cyclonedds.util import duration

        from mmctl.ros2 import messages

        m: Any = messages  # (cyclonedds' field markers are not types mypy can check)
        self.m = m
        self.cfg = cfg
        self.origin_wall = origin_wall
        r = cfg.ros2
        xml = LOCALHOST_XML if r.discovery_range == "localhost" else SUBNET_XML
        self._domain = Domain(r.domain_id, xml)
        dp = self._dp = DomainParticipant(r.domain_id)
        reliable = Policy.Reliability.Reliable(duration(milliseconds=100))
        state = Qos(reliable, Policy.Durability.Volatile, Policy.History.KeepLast(10))
        tf = Qos(reliable, Policy.Durability.Volatile, Policy.History.KeepLast(100))
        latched = Qos(reliable, Policy.Durability.TransientLocal, Policy.History.KeepLast(1))

        def writer(name: str, typ: type, qos: Any) -> Any:
            topic: Any = Topic(dp, m.dds_topic(topic_name(r.topic_prefix, name)), typ)
            return DataWriter(dp, topic, qos=qos)

        self.topics = {"/joint_states": m.JointState, "/tf": m.TFMessage,
                       "/tf_static": m.TFMessage, "/robot_description": m.String,
                       "mmctl/wrench/raw": m.WrenchStamped,
                       "mmctl/wrench/human": m.WrenchStamped,
                       "mmctl/twist/desired": m.TwistStamped,
                       "/diagnostics": m.DiagnosticArray}
        self._joints = writer("/joint_states", m.JointState, state)
        self._tf = writer("/tf", m.TFMessage, tf)
        self._tf_static = writer("/tf_static", m.TFMessage, latched)
        self._description = writer("/robot_description", m.String, latched)
        self._raw = writer("mmctl/wrench/raw", m.WrenchStamped, state)
        self._wrench = writer("mmctl/wrench/human", m.WrenchStamped, state)
        self._twist = writer("mmctl/twist/desired", m.TwistStamped, state)
        self._diagnostics = writer("/diagnostics", m.DiagnosticArray, state)
        self.model = RobotModel(cfg.robot)
        self._data = self.model.arm.createData()
        self._tool = self.model.frame_id("tool")
        self._origin_xyz = [o.translation.copy() for o in arm_joint_origins()]
        self._links = ["ur_base"] + [link_name(j) for j in range(1, NA + 1)]
        self.published = 0
        self._closed = False
        self._description.write(m.String(urdf(cfg)))
        self._tf_static.write(m.TFMessage(
            [self._transform(0.0, parent, child, origin.translation, _quat(origin.rotation))
             for _, parent, child, origin in fixed_joints(cfg)]))

    # -- messages -----------------------------------------------------------------------
    def _stamp(self, t: float) -> Any:
        return self.m.Time.of(self.origin_wall + t)

    def _transform(self, t: float, parent: str, child: str, xyz: Any,
                   quat: tuple[float, float, float, float]) -> Any:
        m = self.m
        return m.TransformStamped(
            m.Header(self._stamp(t), parent), child,
            m.Transform(m.Vector3(*(float(v) for v in xyz)), m.Quaternion(*quat)))

    def publish(self, row: np.ndarray) -> None:
        """One telemetry row (:mod:`mmctl.telemetry.ring` layout) on the state topics."""
        m = self.m
        t = float(row[tr.T])
        q_a = row[tr.Q_A]
        qd_a = row[tr.QD_A]
        header = m.Header(self._stamp(t), "")
        self._joints.write(m.JointState(
            header, list(ROS_JOINT_NAMES), [float(x) for x in q_a],
            [0.0 if not math.isfinite(x) else float(x) for x in qd_a], []))
        x, y, yaw = (float(v) for v in row[tr.BASE_POSE])
        transforms = [self._transform(t, "odom", "base_link", (x, y, 0.0), yaw_quaternion(yaw))]
        for i, quat in enumerate(arm_joint_quaternions(q_a).tolist()):
            transforms.append(self._transform(t, self._links[i], self._links[i + 1],
                                              self._origin_xyz[i], tuple(quat)))
        self._tf.write(m.TFMessage(transforms))
        pin.forwardKinematics(self.model.arm, self._data, np.asarray(q_a, dtype=float))
        rot = pin.updateFramePlacement(self.model.arm, self._data, self._tool).rotation
        handle = m.Header(self._stamp(t), "handle")
        f = rot.T @ np.asarray(row[tr.F_H][:3]), rot.T @ np.asarray(row[tr.F_H][3:])
        self._wrench.write(m.WrenchStamped(handle, m.Wrench(
            m.Vector3(*map(float, f[0])), m.Vector3(*map(float, f[1])))))
        raw = [float(x) for x in row[tr.F_RAW]]
        self._raw.write(m.WrenchStamped(m.Header(self._stamp(t), "sensor"), m.Wrench(
            m.Vector3(*raw[:3]), m.Vector3(*raw[3:]))))
        v = rot.T @ np.asarray(row[tr.V_D][:3]), rot.T @ np.asarray(row[tr.V_D][3:])
        self._twist.write(m.TwistStamped(handle, m.Twist(
            m.Vector3(*map(float, v[0])), m.Vector3(*map(float, v[1])))))
        self.published += 1

    def publish_diagnostics(self, row: np.ndarray, timing: dict[str, float]) -> None:
        """/diagnostics: the newest row's state and the loop's timing since the last."""
        m = self.m
        safety = tr.label(tr.SAFETY_STATES, float(row[tr.SAFETY]))
        level = m.ERROR if safety == "fault" else m.OK
        values = {
            "state": safety, "mode": tr.label(tr.MODES, float(row[tr.MODE])),
            "limit": tr.label(tr.LIMITS, float(row[tr.LIMIT])) or "-",
            "limit_scale": f"{float(row[tr.LIMIT_SCALE]):.3f}",
            "kinetic_energy_J": f"{float(row[tr.E_TOTAL]):.4f}",
            "nearest_parts_m": f"{float(row[tr.NEAREST]):.4f}",
            "cycle_compute_p50_us": f"{timing.get('compute_p50_us', math.nan):.0f}",
            "cycle_compute_p99_us": f"{timing.get('compute_p99_us', math.nan):.0f}",
            "cycle_misses": f"{int(timing.get('misses', 0))}",
            "cycles": f"{int(timing.get('cycles', 0))}",
        }
        status = m.DiagnosticStatus(level, "mmctl: controller", safety, "mmctl",
                                    [m.KeyValue(k, v) for k, v in values.items()])
        self._diagnostics.write(m.DiagnosticArray(m.Header(self._stamp(float(row[tr.T])), ""),
                                                  [status]))

    def close(self) -> None:
        """Leave the graph (idempotent)."""
        if self._closed:
            return
        self._closed = True
        from cyclonedds.core import DDSException

        try:
            self._dp.__del__()  # deletes the participant and its writers now
        except (DDSException, AttributeError):
            pass
