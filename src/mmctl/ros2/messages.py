"""ROS 2 messages as DDS types: cyclonedds IDL classes with the names ROS 2's ``rmw``
layers give them, so a stock ROS 2 node (Fast DDS or Cyclone DDS underneath) reads
them without any mmctl code.

ROS 2 maps a message ``pkg/msg/Name`` to the DDS type ``pkg::msg::dds_::Name_`` and a
topic ``/name`` to the DDS topic ``rt/name``; fields keep their names, order and types
(``float64`` -> double, ``T[]`` -> sequence, ``string`` -> unbounded string, ``byte``
-> octet), and the types are final (plain CDR, little-endian).  The definitions follow
the message files of Jazzy's ``builtin_interfaces``, ``std_msgs``, ``sensor_msgs``,
``geometry_msgs``, ``tf2_msgs`` and ``diagnostic_msgs``;
``tests/test_ros2_messages.py`` decodes our bytes with an independent CDR decoder
(rosbags) from those message files.

(No ``from __future__ import annotations`` here: cyclonedds reads the field types from
the evaluated annotations.)
"""

import math
from dataclasses import dataclass, field

from cyclonedds.idl import IdlStruct
from cyclonedds.idl import types as t


def dds_topic(name: str) -> str:
    """A ROS 2 topic name as its DDS topic name (``/joint_states`` -> ``rt/joint_states``)."""
    return "rt" + (name if name.startswith("/") else "/" + name)


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32 = 0
    nanosec: t.uint32 = 0

    @classmethod
    def of(cls, seconds: float) -> "Time":
        """A wall-clock time [s since the epoch] as ROS 2's (sec, nanosec)."""
        whole = math.floor(seconds)
        return cls(int(whole), min(999_999_999, round((seconds - whole) * 1e9)))


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str = ""


@dataclass
class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header = field(default_factory=Header)
    name: t.sequence[str] = field(default_factory=list)
    position: t.sequence[t.float64] = field(default_factory=list)
    velocity: t.sequence[t.float64] = field(default_factory=list)
    effort: t.sequence[t.float64] = field(default_factory=list)


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64 = 0.0
    y: t.float64 = 0.0
    z: t.float64 = 0.0
    w: t.float64 = 1.0


@dataclass
class Transform(IdlStruct, typename="geometry_msgs::msg::dds_::Transform_"):
    translation: Vector3 = field(default_factory=Vector3)
    rotation: Quaternion = field(default_factory=Quaternion)


@dataclass
class TransformStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TransformStamped_"):
    header: Header = field(default_factory=Header)
    child_frame_id: str = ""
    transform: Transform = field(default_factory=Transform)


@dataclass
class TFMessage(IdlStruct, typename="tf2_msgs::msg::dds_::TFMessage_"):
    transforms: t.sequence[TransformStamped] = field(default_factory=list)


@dataclass
class Wrench(IdlStruct, typename="geometry_msgs::msg::dds_::Wrench_"):
    force: Vector3 = field(default_factory=Vector3)
    torque: Vector3 = field(default_factory=Vector3)


@dataclass
class WrenchStamped(IdlStruct, typename="geometry_msgs::msg::dds_::WrenchStamped_"):
    header: Header = field(default_factory=Header)
    wrench: Wrench = field(default_factory=Wrench)


@dataclass
class Twist(IdlStruct, typename="geometry_msgs::msg::dds_::Twist_"):
    linear: Vector3 = field(default_factory=Vector3)
    angular: Vector3 = field(default_factory=Vector3)


@dataclass
class TwistStamped(IdlStruct, typename="geometry_msgs::msg::dds_::TwistStamped_"):
    header: Header = field(default_factory=Header)
    twist: Twist = field(default_factory=Twist)


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str = ""
    value: str = ""


#: diagnostic_msgs/DiagnosticStatus levels (constants of the message, not fields)
OK, WARN, ERROR, STALE = 0, 1, 2, 3


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: t.byte = 0
    name: str = ""
    message: str = ""
    hardware_id: str = ""
    values: t.sequence[KeyValue] = field(default_factory=list)


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header = field(default_factory=Header)
    status: t.sequence[DiagnosticStatus] = field(default_factory=list)


#: the ROS 2 name of each type (``pkg/msg/Name``), for the docs and the tests
ROS_NAMES: dict[type, str] = {
    cls: cls.__idl_typename__.replace("::dds_::", "/").replace("::", "/").rstrip("_")
    for cls in (Time, Header, String, JointState, Vector3, Quaternion, Transform,
                TransformStamped, TFMessage, Wrench, WrenchStamped, Twist, TwistStamped,
                KeyValue, DiagnosticStatus, DiagnosticArray)
}
