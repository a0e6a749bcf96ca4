"""Run inside a private network namespace by tests/test_ros2_bridge.py: the daemon on
its simulated robot with the ROS 2 bridge on, and a real rclpy node (the ros-rclpy
Jazzy wheels) that subscribes to the bridge's topics.  Writes what it saw as JSON.

usage: python tests/ros2_probe.py CONFIG SOCKET OUT.json SECONDS
"""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any


def main(config: str, sock: str, out: str, seconds: float) -> int:
    from mmctl.runtime.ipc import request

    mmctl = Path(sys.executable).parent / "mmctl"
    log = open(Path(out).with_suffix(".daemon.log"), "w")  # noqa: SIM115
    daemon = subprocess.Popen([str(mmctl), "run", "--config", config, "--socket", sock],
                              stdout=log, stderr=subprocess.STDOUT)
    result: dict[str, Any] = {}
    try:
        deadline = time.monotonic() + 180.0
        status: dict[str, Any] = {}
        while time.monotonic() < deadline:
            try:
                status = request(sock, "status", timeout=30.0)
                if status.get("state") == "armed":
                    break
            except Exception:  # noqa: BLE001, S110 -- not up yet
                pass
            time.sleep(0.2)
        result["armed"] = status.get("state") == "armed"
        result.update(_listen(seconds, lambda: request(sock, "status", timeout=30.0)))
    finally:
        daemon.send_signal(signal.SIGINT)
        try:
            result["daemon_rc"] = daemon.wait(60)
        except subprocess.TimeoutExpired:
            daemon.kill()
            result["daemon_rc"] = None
        log.close()
    Path(out).write_text(json.dumps(result))
    return 0


def _listen(seconds: float, status: Any) -> dict[str, Any]:
    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import TwistStamped, WrenchStamped
    from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import JointState
    from std_msgs.msg import String

    rclpy.init()
    node = rclpy.create_node("mmctl_test_listener")
    latched = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL,
                         history=HistoryPolicy.KEEP_LAST)
    got: dict[str, Any] = {"joint_states": [], "latency_ms": [], "description": None,
                           "wrench": None, "raw": None, "twist": None, "diagnostics": None}

    def on_joints(msg: JointState) -> None:
        now = time.time()
        stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
        got["latency_ms"].append(1e3 * (now - stamp))
        got["joint_states"].append({"name": list(msg.name), "position": list(msg.position),
                                    "velocity": list(msg.velocity), "stamp": stamp})

    def on_wrench(msg: WrenchStamped) -> None:
        f, tq = msg.wrench.force, msg.wrench.torque
        got["wrench"] = {"frame": msg.header.frame_id, "force": [f.x, f.y, f.z],
                         "torque": [tq.x, tq.y, tq.z]}

    def on_twist(msg: TwistStamped) -> None:
        v = msg.twist.linear
        got["twist"] = {"frame": msg.header.frame_id, "linear": [v.x, v.y, v.z]}

    def on_diag(msg: DiagnosticArray) -> None:
        got["diagnostics"] = [{"name": s.name, "level": int.from_bytes(s.level, "little")
                               if isinstance(s.level, bytes) else int(s.level),
                               "message": s.message,
                               "values": {kv.key: kv.value for kv in s.values}}
                              for s in msg.status]

    def on_description(msg: String) -> None:
        got["description"] = msg.data

    node.create_subscription(JointState, "/joint_states", on_joints, 50)
    node.create_subscription(WrenchStamped, "/mmctl/wrench/human", on_wrench, 10)

    def on_raw(msg: WrenchStamped) -> None:
        f, tq = msg.wrench.force, msg.wrench.torque
        got["raw"] = {"frame": msg.header.frame_id, "force": [f.x, f.y, f.z],
                      "torque": [tq.x, tq.y, tq.z]}

    node.create_subscription(WrenchStamped, "/mmctl/wrench/raw", on_raw, 10)
    node.create_subscription(TwistStamped, "/mmctl/twist/desired", on_twist, 10)
    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    node.create_subscription(String, "/robot_description", on_description, latched)
    # at least ``seconds``, and until every topic has spoken and 20 joint states came: on
    # a busy machine the bridge (background work: SCHED_IDLE) gets little CPU, so this
    # waits for counts, not times (at most 5 minutes)
    start = time.monotonic()
    end = start + seconds

    def heard() -> bool:
        return (len(got["joint_states"]) >= 20
                and all(got[k] is not None for k in ("description", "wrench", "raw", "twist",
                                                     "diagnostics")))

    while time.monotonic() < end or not heard() and time.monotonic() < start + 300:
        rclpy.spin_once(node, timeout_sec=0.05)
    # the same moment: a status, then the next joint state (the robot is at rest)
    st = status()
    n = len(got["joint_states"])
    while len(got["joint_states"]) == n and time.monotonic() < start + 360:
        rclpy.spin_once(node, timeout_sec=0.05)
    graph = {name: types for name, types in node.get_topic_names_and_types()}
    node.destroy_node()
    rclpy.shutdown()
    lat = sorted(got.pop("latency_ms"))
    joints = got.pop("joint_states")
    return {**got, "graph": graph, "status": st, "joint_count": len(joints),
            "joints_first": joints[0] if joints else None,
            "joints_last": joints[-1] if joints else None,
            "latency_p50_ms": lat[len(lat) // 2] if lat else math.nan,
            "latency_p99_ms": lat[min(len(lat) - 1, int(0.99 * len(lat)))] if lat else math.nan,
            "tf": _tf(3.0)}


def _tf(seconds: float) -> dict[str, Any]:
    """/tf and /tf_static through a plain DDS reader (tf2_msgs has no wheel on PyPI, so
    rclpy cannot subscribe to it here): each child frame's parent and transform."""
    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import Domain, DomainParticipant
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    from mmctl.ros2 import messages as m
    from mmctl.ros2.bridge import LOCALHOST_XML

    domain = Domain(0, LOCALHOST_XML)  # (kept: the domain lives as long as this object)
    dp = DomainParticipant(0)
    reliable = Policy.Reliability.Reliable(duration(milliseconds=100))
    readers = [DataReader(dp, Topic(dp, "rt/tf", m.TFMessage),
                          qos=Qos(reliable, Policy.Durability.Volatile,
                                  Policy.History.KeepLast(100))),
               DataReader(dp, Topic(dp, "rt/tf_static", m.TFMessage),
                          qos=Qos(reliable, Policy.Durability.TransientLocal,
                                  Policy.History.KeepLast(1)))]
    frames: dict[str, Any] = {}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for r in readers:
            for msg in r.take(N=100):
                for ts in msg.transforms:
                    tr, rot = ts.transform.translation, ts.transform.rotation
                    frames[ts.child_frame_id] = {
                        "parent": ts.header.frame_id, "xyz": [tr.x, tr.y, tr.z],
                        "xyzw": [rot.x, rot.y, rot.z, rot.w]}
        time.sleep(0.02)
    del domain
    return frames


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2], sys.argv[3], float(sys.argv[4])))
