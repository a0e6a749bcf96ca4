"""The ROS 2 bridge's messages (src/mmctl/ros2/messages.py): the bytes cyclonedds
writes for each, decoded by an independent CDR decoder (rosbags, pure Python, from
Jazzy's own message definitions), give back every field; the type and topic names are
ROS 2's."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("cyclonedds", reason="the ROS 2 bridge's extra (mmctl[ros2])")
rosbags_typesys = pytest.importorskip("rosbags.typesys", reason="rosbags (the test extra)")

from mmctl.ros2 import messages as m

STORE = rosbags_typesys.get_typestore(rosbags_typesys.Stores.ROS2_JAZZY)
STAMP = m.Time.of(1764331200.125)


def _decode(msg: object) -> object:
    name = m.ROS_NAMES[type(msg)]
    return STORE.deserialize_cdr(msg.serialize(), name)  # type: ignore[attr-defined]


def _vec(v: object) -> list[float]:
    return [v.x, v.y, v.z]  # type: ignore[attr-defined]


def test_the_dds_names_are_ros2s() -> None:
    assert m.JointState.__idl_typename__ == "sensor_msgs::msg::dds_::JointState_"  # type: ignore[attr-defined]
    assert m.ROS_NAMES[m.TFMessage] == "tf2_msgs/msg/TFMessage"
    assert m.ROS_NAMES[m.DiagnosticArray] == "diagnostic_msgs/msg/DiagnosticArray"
    assert set(m.ROS_NAMES.values()) <= set(STORE.types)  # every one is a Jazzy message
    assert m.dds_topic("/joint_states") == "rt/joint_states"
    assert m.dds_topic("mmctl/wrench/human") == "rt/mmctl/wrench/human"


def test_time_splits_seconds_into_sec_and_nanosec() -> None:
    assert (STAMP.sec, STAMP.nanosec) == (1764331200, 125_000_000)
    assert m.Time.of(2.9999999999).nanosec <= 999_999_999


def test_joint_state() -> None:
    msg = m.JointState(m.Header(STAMP, "base_link"), ["shoulder_pan_joint", "elbow_joint"],
                       [0.1, -1.9], [0.01, math.pi], [])
    d = _decode(msg)
    assert (d.header.stamp.sec, d.header.stamp.nanosec) == (STAMP.sec, STAMP.nanosec)  # type: ignore[attr-defined]
    assert d.header.frame_id == "base_link"  # type: ignore[attr-defined]
    assert d.name == ["shoulder_pan_joint", "elbow_joint"]  # type: ignore[attr-defined]
    assert list(d.position) == [0.1, -1.9] and list(d.velocity) == [0.01, math.pi]  # type: ignore[attr-defined]
    assert len(d.effort) == 0  # type: ignore[attr-defined]


def test_tf_message_of_two_transforms() -> None:
    a = m.TransformStamped(m.Header(STAMP, "odom"), "base_link",
                           m.Transform(m.Vector3(1.0, 2.0, 0.0), m.Quaternion(0.0, 0.0, 0.6, 0.8)))
    b = m.TransformStamped(m.Header(STAMP, "flange"), "handle",
                           m.Transform(m.Vector3(0.0, 0.0, 0.15), m.Quaternion()))
    d = _decode(m.TFMessage([a, b]))
    t0, t1 = d.transforms  # type: ignore[attr-defined]
    assert (t0.header.frame_id, t0.child_frame_id) == ("odom", "base_link")
    assert _vec(t0.transform.translation) == [1.0, 2.0, 0.0]
    q = t0.transform.rotation
    assert [q.x, q.y, q.z, q.w] == [0.0, 0.0, 0.6, 0.8]
    assert (t1.header.frame_id, t1.child_frame_id) == ("flange", "handle")
    assert t1.transform.rotation.w == 1.0


def test_wrench_and_twist_stamped() -> None:
    w = _decode(m.WrenchStamped(m.Header(STAMP, "handle"),
                                m.Wrench(m.Vector3(30.0, -5.0, 2.0), m.Vector3(0.1, 0.2, 0.3))))
    assert w.header.frame_id == "handle"  # type: ignore[attr-defined]
    assert _vec(w.wrench.force) == [30.0, -5.0, 2.0]  # type: ignore[attr-defined]
    assert _vec(w.wrench.torque) == [0.1, 0.2, 0.3]  # type: ignore[attr-defined]
    tw = _decode(m.TwistStamped(m.Header(STAMP, "handle"),
                                m.Twist(m.Vector3(0.2, 0.0, 0.0), m.Vector3(0.0, 0.0, -0.5))))
    assert _vec(tw.twist.linear) == [0.2, 0.0, 0.0] and tw.twist.angular.z == -0.5  # type: ignore[attr-defined]


def test_string_and_diagnostics() -> None:
    text = '<?xml version="1.0"?>\n<robot name="r">… ü</robot>\n'
    assert _decode(m.String(text)).data == text  # type: ignore[attr-defined]
    status = m.DiagnosticStatus(m.ERROR, "mmctl: controller", "fault", "mmctl",
                                [m.KeyValue("state", "fault"), m.KeyValue("cycles", "100")])
    d = _decode(m.DiagnosticArray(m.Header(STAMP, ""), [status, m.DiagnosticStatus()]))
    s0, s1 = d.status  # type: ignore[attr-defined]
    assert (s0.level, s0.name, s0.message, s0.hardware_id) == (2, "mmctl: controller", "fault",
                                                               "mmctl")
    assert [(kv.key, kv.value) for kv in s0.values] == [("state", "fault"), ("cycles", "100")]
    assert s1.level == m.OK and s1.values == []


def test_a_long_joint_state_round_trips_exactly() -> None:
    rng = np.random.default_rng(3)
    pos = rng.normal(size=6).tolist()
    d = _decode(m.JointState(m.Header(STAMP, ""), [f"j{i}" for i in range(6)], pos, pos, pos))
    assert list(d.position) == pos and list(d.effort) == pos  # type: ignore[attr-defined]
